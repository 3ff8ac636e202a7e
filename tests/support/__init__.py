"""Helpers shared by the test modules (``from support.cli import run_cli``); fixtures stay in
``tests/conftest.py``, which re-exports the helpers older modules import from it."""
