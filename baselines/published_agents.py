"""Where the published agents and heads live (a leaf module: ``evaluate`` and ``publish`` both read it, so neither
imports the other back)."""
from __future__ import annotations

from pathlib import Path

PUBLISHED = Path(__file__).resolve().parent / "published"
"""``baselines/published``: one folder per published agent or slide head."""
