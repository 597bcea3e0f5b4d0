"""`se3sync plot`: the panels of the paper's Fig. 2 (and V̄) from one or more se3sync MCAP logs.

Errors, speeds and V̄ are drawn on log axes by default (they fall exponentially); θ_k is drawn
on a linear axis with an inset on the first instants so that every jump is visible.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from controller.errors import Se3SyncError

from ..files import atomic_path
from .reader import read_log

__all__ = ["load_series", "plot_log", "plot_logs", "make_figure", "LINESTYLES"]

# distinct dash patterns, so that curves that overlap (symmetric edges) stay distinguishable
LINESTYLES = ("-", "--", "-.", ":", (0, (5, 1, 1, 1, 1, 1)), (0, (8, 2)), (0, (1, 3)),
              (0, (3, 1, 3, 1, 1, 1)))
_MARKERS = ("o", "s", "^", "v", "D", "P", "X", "*")


def load_series(path) -> dict:
    """Arrays from a log: t (T,), rot_err/pos_err/theta (T, M), omega/v (T, N, 3),
    t_V/V (V̄ from /lyapunov), jumps, metadata."""
    log = read_log(path, topics=("/edges", "/agents", "/lyapunov", "/jumps"))
    edges = log["messages"].get("/edges", [])
    agents = log["messages"].get("/agents", [])
    if not edges or not agents:
        raise Se3SyncError(f"{path}: the log has no /edges or /agents messages to plot")
    edges.sort(key=lambda m: m[0])
    agents.sort(key=lambda m: m[0])
    lyap = sorted(log["messages"].get("/lyapunov", []), key=lambda m: m[0])
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
        "t_V": np.array([m[0] for m in lyap]) * 1e-9,
        "V": np.array([m[1]["V"] if m[1].get("V") is not None else np.nan for m in lyap], float),
        "jumps": [m[1] for m in log["messages"].get("/jumps", [])],
        "metadata": log["metadata"],
        # the numbers the log gives its edges and agents (an agent process's log of its
        # neighbourhood uses the swarm's)
        "edge_ids": [e.get("edge", k + 1) for k, e in enumerate(edges[0][1]["edges"])],
        "agent_ids": [a.get("agent", i + 1) for i, a in enumerate(agents[0][1]["agents"])],
    }
    return out


def _positive(y):
    """Log axes cannot show 0: exact zeros become gaps."""
    y = np.array(y, float)
    y[~(y > 0)] = np.nan
    return y


def make_figure(paths, labels=None, *, linear=False, tmin=None, tmax=None):
    """The matplotlib figure for one log or an overlay of several (Agg backend).

    One log: edge/agent k gets colour C(k) and dash pattern k. Several logs: run r gets colour
    C(r), edge/agent k gets dash pattern k. Axes: ‖I − R̄_k‖_F, ‖p̄_k‖, ‖ω_i‖, ‖v_i‖, V̄ (log unless
    ``linear``) and θ_k (linear, with an inset on the first jumps and the jumps as markers).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    paths = [str(p) for p in paths]
    if labels is None:
        labels = [Path(p).stem for p in paths] if len(paths) > 1 else [None]
    if len(labels) != len(paths):
        raise Se3SyncError(f"--labels: {len(labels)} labels for {len(paths)} logs")
    runs = [load_series(p) for p in paths]
    if tmin is not None and tmax is not None and not tmax > tmin:
        raise Se3SyncError(f"--tmax: must be greater than --tmin ({tmin:g}), got {tmax:g}")
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    multi = len(runs) > 1

    fig, axes = plt.subplots(6, 1, figsize=(8, 14), sharex=True)
    ax_R, ax_p, ax_w, ax_v, ax_V, ax_th = axes
    ins = ax_th.inset_axes([0.55, 0.35, 0.42, 0.6])
    early_end = 0.0
    for r, (d, lab) in enumerate(zip(runs, labels)):
        t, ta = d["t"], d["t_agents"]
        M = d["rot_err"].shape[1]
        N = d["omega"].shape[1]
        eid, aid = d["edge_ids"], d["agent_ids"]
        pre = f"{lab}: " if multi else ""

        def style(k):
            c = colors[r % len(colors)] if multi else colors[k % len(colors)]
            return {"color": c, "ls": LINESTYLES[k % len(LINESTYLES)], "lw": 1.2}

        tr = _positive if not linear else np.asarray

        def curve(a, x, y, label, name, st):
            """A curve on axes a; on a log axis one with nothing to show (exactly zero, e.g.
            the gradient baseline's velocities at a critical point) gets no legend entry of
            its own but is named in one "≡ 0" entry per run and axes."""
            y = tr(y)
            if not linear and not np.isfinite(y).any():
                zero.setdefault((id(a), r), (a, st, []))[2].append(name)
                label = None
            a.plot(x, y, label=label, **st)

        zero = {}
        for k in range(M):
            curve(ax_R, t, d["rot_err"][:, k], f"{pre}k={eid[k]}", f"k={eid[k]}", style(k))
            curve(ax_p, t, d["pos_err"][:, k], f"{pre}k={eid[k]}", f"k={eid[k]}", style(k))
            ax_th.plot(t, d["theta"][:, k], label=f"{pre}k={eid[k]}", **style(k))
            ins.plot(t, d["theta"][:, k], **style(k))
        for i in range(N):
            curve(ax_w, ta, np.linalg.norm(d["omega"][:, i], axis=1), f"{pre}i={aid[i]}",
                  f"i={aid[i]}", style(i))
            curve(ax_v, ta, np.linalg.norm(d["v"][:, i], axis=1), f"{pre}i={aid[i]}",
                  f"i={aid[i]}", style(i))
        if len(d["V"]):
            curve(ax_V, d["t_V"], d["V"], f"{lab}" if multi else r"$\bar V$",
                  f"{lab}" if multi else "V", {"color": colors[r % len(colors)],
                                               "ls": LINESTYLES[r % len(LINESTYLES)]})
        for a, st, names in zero.values():
            every = ", ".join(names) if len(names) <= 3 else f"{names[0]}…{names[-1]}"
            a.plot([], [], color=st["color"] if multi else "0.4", ls="none", marker="_",
                   label=f"{pre}{every} ≡ 0 (not on the log axis)")
        # the jumps: a vertical segment from θ⁻ to θ⁺ and a marker at θ⁺, per edge
        for k in range(M):
            js = [j for j in d["jumps"] if j.get("edge") == eid[k]]
            if not js:
                continue
            tj = np.array([j["t"] for j in js], float)
            before = np.array([j["theta_before"] for j in js], float)
            after = np.array([j["theta_after"] for j in js], float)
            st = style(k)
            for a in (ax_th, ins):
                a.vlines(tj, before, after, color=st["color"], lw=0.8, alpha=0.7)
                a.plot(tj, after, ls="none", marker=_MARKERS[k % len(_MARKERS)], ms=5,
                       mfc="none", color=st["color"],
                       label=f"{pre}jump k={eid[k]} ({len(js)})" if a is ax_th else None)
            early = tj[tj <= 1.0 + (tmin or 0.0)]
            if len(early):
                early_end = max(early_end, float(early.max()))
    first, last = min(float(d["t"][0]) for d in runs), max(float(d["t"][-1]) for d in runs)
    if (tmin is not None and tmin >= last) or (tmax is not None and tmax <= first):
        raise Se3SyncError(f"--tmin/--tmax: the window is outside the log ({first:g}..{last:g} s)")
    t_lo = tmin if tmin is not None else first
    t_hi = tmax if tmax is not None else last
    if t_hi > t_lo:
        for a in axes:
            a.set_xlim(t_lo, t_hi)
    # inset: the first instants, wide enough to separate the early jumps
    span = max(0.05, 1.25 * (early_end - t_lo)) if early_end > t_lo else min(1.0, t_hi - t_lo)
    span = span if span > 0 else 1.0
    # a margin before t_lo, so that the jumps at the first instant are not cut by the frame
    ins.set_xlim(t_lo - 0.04 * span, t_lo + span)
    # the title inside the inset: above it, it ran into the panel above
    ins.text(0.02, 0.97, f"first {span:.3g} s", transform=ins.transAxes, fontsize=7,
             va="top", ha="left", bbox=dict(boxstyle="round,pad=0.2", fc="white", ec="none",
                                             alpha=0.8))
    ins.tick_params(labelsize=6)
    ins.grid(True, alpha=0.3)
    ylab = [r"$\|I-\bar R_k\|_F$", r"$\|\bar p_k\|$ (m)", r"$\|\omega_i\|$ (rad/s)",
            r"$\|v_i\|$ (m/s)", r"$\bar V$", r"$\theta_k$ (rad)"]
    for a, lab in zip(axes, ylab):
        a.set_ylabel(lab)
        a.grid(True, which="both" if not linear else "major", alpha=0.25)
        if not linear and a is not ax_th:
            a.set_yscale("log")
    for a in axes:
        h, l = a.get_legend_handles_labels()
        if h:
            a.legend(loc="upper left" if a is ax_th else "upper right", fontsize=6,
                     ncol=3 if a is not ax_th else 2, framealpha=0.8)
    ax_th.set_xlabel("t (s, simulated)")
    names = [(d["metadata"] or {}).get("scenario_name", Path(p).stem) for d, p in zip(runs, paths)]
    title = " vs ".join(f"{lab} ({n})" if lab else n for lab, n in zip(labels, names))
    ax_R.set_title(f"se3sync: {title}", fontsize=9)
    fig.tight_layout()
    return fig


def plot_logs(paths, out, labels=None, *, linear=False, tmin=None, tmax=None,
              dpi: int = 150) -> Path:
    """Writes the figure of ``make_figure`` (format from the suffix: png, pdf, svg; PNG if
    none) atomically; returns its path."""
    import matplotlib.pyplot as plt

    fig = make_figure(paths, labels, linear=linear, tmin=tmin, tmax=tmax)
    out = Path(out)
    fmt = out.suffix.lstrip(".").lower() or "png"
    try:
        with atomic_path(out) as tmp, open(tmp, "wb") as f:
            fig.savefig(f, format=fmt, dpi=dpi)
    finally:
        plt.close(fig)
    return out


def plot_log(path, out, *, dpi: int = 150, **kw) -> Path:
    """One log (see ``plot_logs``)."""
    return plot_logs([path], out, dpi=dpi, **kw)
