"""Scenario texts for stability tests and benchmarks: the HIL design on any tree.

`tree_scenario_text(N, kind, seed)` keeps scenarios/hil_6uav.toml's vehicles, weighting and
gains and replaces its graph: a chain, or a random tree (each agent k ≥ 2 joins a uniformly
random earlier agent, seeded, with a random orientation).
"""
from __future__ import annotations

import os
import re

import numpy as np

HIL = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))),
                   "scenarios", "hil_6uav.toml")


def tree_edges(N: int, kind: str = "random", seed: int = 0) -> list:
    """1-based (positive, negative) edges of a chain or a seeded random tree on N agents."""
    if kind == "chain":
        return [[k, k + 1] for k in range(1, N)]
    rng = np.random.default_rng(seed)
    out = []
    for k in range(2, N + 1):
        p = int(rng.integers(1, k))
        out.append([p, k] if rng.random() < 0.5 else [k, p])
    return out


def tree_scenario_text(N: int, kind: str = "random", seed: int = 0, masses=None) -> str:
    text = open(HIL).read().split("[bridge]")[0]     # no MAVLink ids for thousands of agents
    text = re.sub(r"count = \d+", f"count = {N}", text, count=1)
    text = re.sub(r"edges = \[\[.*\]\]", "edges = " + str(tree_edges(N, kind, seed)), text, count=1)
    if masses is not None:
        text = text.replace("mass = 2.4", "mass = " + str([float(m) for m in masses]), 1)
    text = text.replace('generator = "paper"\naxis = [0.2997, 0.8380, 0.4560]',
                        'generator = "random"\nseed = 1', 1)
    return text
