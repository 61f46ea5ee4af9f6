"""Helpers the test folders share, imported as `tests.support.NAME` (tests/README.md lists them)."""
