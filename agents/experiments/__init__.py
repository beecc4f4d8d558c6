"""Benchmarks and paper experiments as importable functions; ``scripts/`` are thin CLIs over them.

How the modules are laid out: docs/experiments.md, section "The package".
"""
