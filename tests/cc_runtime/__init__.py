"""Tests and helpers that run inside the real CloudCompare 2.13 + PythonRuntime."""
