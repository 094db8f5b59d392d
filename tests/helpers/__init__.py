"""Helpers shared by the tests (free ports, fixtures' building blocks)."""
