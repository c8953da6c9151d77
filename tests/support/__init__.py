"""Test support shared by tests/ and bench/: code that drives the product but is not part of it.

It lives under tests/ so the wheel never ships it (`[tool.setuptools.packages.find]` includes
only the product's packages). Tests import it as `support.<module>` because pytest puts tests/
on sys.path (tests/ has no __init__.py; conftest.py is imported the same way); a bench script
inserts the repository's tests/ directory into sys.path first.
"""
