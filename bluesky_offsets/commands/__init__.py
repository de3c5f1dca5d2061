"""The command line: its verbs (demo, diagnose, find, surrogate), the report and its figures."""
