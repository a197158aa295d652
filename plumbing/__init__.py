"""The ground floor every layer stands on: nothing domain-specific lives here.

- `plumbing.atomic`: atomic file writes (temp file, fsync, link or rename); one overwrite default.
- `plumbing.config`: data-only config files (TOML/JSON) into strict pydantic models, with
  one-line errors naming the file, the key and what is allowed.
- `plumbing.errors`: `UserError`, the base of every "you can fix this" error; the command line
  turns it into one line and exit 2.
- `plumbing.progress`: one progress-bar helper.

It imports nothing else of ours (import-linter keeps it so).
"""
