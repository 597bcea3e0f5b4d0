"""`se3sync plot`: the panels of the paper's Fig. 2 from an se3sync MCAP log."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from controller.errors import Se3SyncError

from ..files import atomic_path
from .mcap import read_log

__all__ = ["load_series", "plot_log"]


def load_series(path) -> dict:
    """Arrays from a log: t (T,), rot_err/pos_err/theta (T, M), omega/v (T, N, 3), jumps."""
    log = read_log(path)
    edges = log["messages"].get("/edges", [])
    agents = log["messages"].get("/agents", [])
    if not edges or not agents:
        raise Se3SyncError(f"{path}: the log has no /edges or /agents messages to plot")
    edges.sort(key=lambda m: m[0])
    agents.sort(key=lambda m: m[0])
    t = np.array([m[0] for m in edges]) * 1e-9
    ta = np.array([m[0] for m in agents]) * 1e-9

    def col(msgs, key):
        return np.array([[e[key] if e[key] is not None else np.nan for e in m[1]["edges"]]
                         for m in msgs], float)

    out = {
        "t": t, "t_agents": ta,
        "rot_err": col(edges, "rot_err"), "pos_err": col(edges, "pos_err"),
        "theta": col(edges, "theta"),
        "omega": np.array([[a["omega"] for a in m[1]["agents"]] for m in agents], float),
        "v": np.array([[a["v"] for a in m[1]["agents"]] for m in agents], float),
        "jumps": [m[1] for m in log["messages"].get("/jumps", [])],
        "metadata": log["metadata"],
    }
    return out


def plot_log(path, out, *, dpi: int = 110) -> Path:
    """Writes the figure (format from the suffix, PNG by default) atomically; returns its path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    d = load_series(path)
    t, ta = d["t"], d["t_agents"]
    fig, axes = plt.subplots(5, 1, figsize=(8, 12), sharex=True)
    M = d["rot_err"].shape[1]
    N = d["omega"].shape[1]
    for k in range(M):
        axes[0].plot(t, d["rot_err"][:, k], label=f"k={k + 1}")
        axes[1].plot(t, d["pos_err"][:, k], label=f"k={k + 1}")
        axes[4].plot(t, d["theta"][:, k], label=f"k={k + 1}")
    for i in range(N):
        axes[2].plot(ta, np.linalg.norm(d["omega"][:, i], axis=1), label=f"i={i + 1}")
        axes[3].plot(ta, np.linalg.norm(d["v"][:, i], axis=1), label=f"i={i + 1}")
    labels = [r"$\|I-\bar R_k\|_F$", r"$\|\bar p_k\|$ (m)", r"$\|\omega_i\|$ (rad/s)",
              r"$\|v_i\|$ (m/s)", r"$\theta_k$ (rad)"]
    for ax, lab in zip(axes, labels):
        ax.set_ylabel(lab)
        ax.grid(True, alpha=0.3)
        ax.legend(loc="upper right", fontsize=7, ncol=3)
    for j in d["jumps"]:
        axes[4].axvline(j["t"], color="k", alpha=0.15, lw=0.8)
    axes[-1].set_xlabel("t (s, simulated)")
    name = (d["metadata"] or {}).get("scenario_name", Path(path).stem)
    axes[0].set_title(f"se3sync: {name}")
    fig.tight_layout()
    out = Path(out)
    fmt = out.suffix.lstrip(".").lower() or "png"
    try:
        with atomic_path(out) as tmp, open(tmp, "wb") as f:
            fig.savefig(f, format=fmt, dpi=dpi)
    finally:
        plt.close(fig)
    return out
