"""Where things are, for tests at any depth of the tree."""

from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
"""The repository root (the checkout)."""
