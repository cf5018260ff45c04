"""The deployment pairs: which source task a CDT is pretrained on and which target it meets."""

from __future__ import annotations

# Source -> target task of each deployment pair of the paper (and PointGoal, ours).
PAIRS: dict[str, tuple[str, str]] = {
    "CG1-CG2": ("CarGoal1", "CarGoal2"),
    "CC1-CC2": ("CarCircle1", "CarCircle2"),
    "PC1-PC2": ("PointCircle1", "PointCircle2"),
    "PG1-PG2": ("PointGoal1", "PointGoal2"),
}


def parse_pair(pair: str) -> tuple[str, str]:
    """(source task, target task) of a pair name such as `CG1-CG2`; ValueError lists the valid."""
    if pair not in PAIRS:
        raise ValueError(f"unknown pair {pair!r}; valid pairs: {', '.join(PAIRS)}")
    return PAIRS[pair]
