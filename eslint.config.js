// ESLint for the browser console (web/): `make lint` runs it.
import js from "@eslint/js";
import globals from "globals";

export default [
  js.configs.recommended,
  {
    files: ["web/**/*.js"],
    languageOptions: {
      ecmaVersion: 2023,
      sourceType: "module",
      globals: { ...globals.browser, VideoDecoder: "readonly", EncodedVideoChunk: "readonly", AudioDecoder: "readonly", AudioEncoder: "readonly", EncodedAudioChunk: "readonly", AudioData: "readonly", uPlot: "readonly" },
    },
    rules: {
      "no-unused-vars": ["error", { args: "none", caughtErrors: "none" }],
      "prefer-const": "error",
      "eqeqeq": ["error", "smart"],
      "no-var": "error",
    },
  },
  {
    files: ["web/video-worker.js", "web/*-worker.js"],
    languageOptions: { sourceType: "module", globals: { ...globals.worker, VideoDecoder: "readonly", EncodedVideoChunk: "readonly" } },
  },
];
