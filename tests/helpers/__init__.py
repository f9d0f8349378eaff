"""Code that several test files share (a test file never imports another test file): each module
here is imported as ``from helpers.<module> import ...`` (pyproject's pytest ``pythonpath``
puts ``tests/`` on the path)."""
