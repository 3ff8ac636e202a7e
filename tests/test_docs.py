"""The README and docs/: generated references current, every relative link resolves."""

from __future__ import annotations

import re
from pathlib import Path

from brasidas import docs_reference

ROOT = Path(__file__).resolve().parent.parent
PAGES = [ROOT / "README.md", ROOT / "CHANGELOG.md", *sorted((ROOT / "docs").rglob("*.md"))]
LINK = re.compile(r"\]\(([^)\s]+)\)")


def _anchors(page: Path) -> set[str]:
    """GitHub's heading anchors: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"```.*?```", "", page.read_text(encoding="utf-8"), flags=re.S)
    headings = re.findall(r"^#+\s+(.*)$", text, flags=re.M)
    return {
        re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-") for heading in headings
    }


def test_generated_reference_pages_are_current() -> None:
    for name, build in docs_reference.PAGES.items():
        committed = (docs_reference.DOCS / name).read_text(encoding="utf-8")
        assert committed == build(), f"docs/reference/{name}: run python -m brasidas.docs_reference"
    assert docs_reference.main(["--check"]) == 0


def test_configuration_page_lists_every_section_of_both_daemons() -> None:
    from brasidas.config import PlatformConfig, StationConfig, dump_toml

    page = docs_reference.configuration_page()
    assert dump_toml(PlatformConfig()).rstrip() in page
    assert dump_toml(StationConfig()).rstrip() in page
    assert "[mavlink]" in page
    assert "[foxglove]" in page


def test_every_warning_code_is_explained() -> None:
    codes = docs_reference._warning_codes()
    assert len(codes) >= 12
    missing = [name for name, _, meaning in codes if not meaning]
    assert missing == [], f"add a meaning to brasidas/docs_reference.py for {missing}"
    page = docs_reference.warnings_page()
    assert "| 90.24 | `CONNECTIONS_REFUSED` |" in page


def test_every_relative_link_resolves() -> None:
    broken = []
    for page in PAGES:
        for target in LINK.findall(page.read_text(encoding="utf-8")):
            if re.match(r"[a-z]+:", target):
                continue
            path_part, _, anchor = target.partition("#")
            resolved = (page.parent / path_part).resolve() if path_part else page
            if not resolved.exists():
                broken.append(f"{page.relative_to(ROOT)}: {target}")
            elif anchor and resolved.suffix == ".md" and anchor not in _anchors(resolved):
                broken.append(f"{page.relative_to(ROOT)}: {target} (no such heading)")
    assert broken == []


def test_readme_is_a_newcomers_page() -> None:
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    assert len(readme.splitlines()) <= 200
    for command in ("make demo", "make test", "make test-quick"):
        assert command in readme
    assert "issue 1" not in readme.lower()


def test_every_screenshot_is_linked_from_the_docs() -> None:
    text = "\n".join(page.read_text(encoding="utf-8") for page in PAGES)
    unlinked = [png.name for png in sorted((ROOT / "docs").glob("*.png")) if png.name not in text]
    assert unlinked == []


def test_history_lives_in_the_changelog() -> None:
    """The manual says what is; which issue changed it is CHANGELOG.md's business."""
    generated = {docs_reference.DOCS / name for name in docs_reference.PAGES}
    dated = [
        f"{page.relative_to(ROOT)}:{number}"
        for page in PAGES
        if page.name != "CHANGELOG.md" and page not in generated
        for number, line in enumerate(page.read_text(encoding="utf-8").splitlines(), 1)
        if re.search(r"\bissue \d+|before the fix", line, flags=re.I)
    ]
    assert dated == []
