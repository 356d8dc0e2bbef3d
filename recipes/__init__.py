"""Studies built on the library, each a folder with its entry point, config and pipeline.

Not installed with the library: run a study's ``main.py`` (it makes the repository root
importable), or import it from the repository root in tests and benchmarks.
"""
