"""Shared helpers of the tests: synthetic scenes, small campaign folders, orchestration set-ups."""
