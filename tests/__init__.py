"""The pelvislab test suite."""
