"""What every command shares at the terminal: one-line usage errors and argument types
(``usage``) and the progress-bar protocol (``progress``). Uses only :mod:`imaging`."""
