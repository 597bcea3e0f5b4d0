"""`se3sync animate LOG.mcap -o swarm.mp4|.gif`: a 3D animation of the bodies and graph edges.

Each agent is drawn as the box of its inertia (cosim.log.foxglove.box_size) at its pose from /tf,
each edge as a segment between the two agents' origins coloured by ‖I − R̄_k‖_F (the same
colour scale as the Foxglove scene); the title carries the simulated time and the current max
edge error. Frames are sampled uniformly in simulated time; each shows the latest log record.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from tqdm import tqdm

from controller.errors import Se3SyncError
from controller.se3 import quat_to_rot

from ..files import atomic_path
from .foxglove import ERR_HI, ERR_LO, box_size, error_color, error_colors
from .reader import read_log

__all__ = ["load_poses", "animate_log", "snapshot", "clusters", "nest_scales"]

# box corners (±1/2) and its 6 faces as corner indices
_CORNERS = np.array([[x, y, z] for x in (-.5, .5) for y in (-.5, .5) for z in (-.5, .5)])
_FACES = ((0, 1, 3, 2), (4, 5, 7, 6), (0, 1, 5, 4), (2, 3, 7, 6), (0, 2, 6, 4), (1, 3, 7, 5))


def load_poses(path) -> dict:
    """From a log: t (T,), p (T, N, 3), R (T, N, 3, 3) from /tf; t_e, rot_err (T_e, M) from
    /edges; edges (M, 2) 1-based; box (N, 3) edge lengths of each body."""
    import json


    log = read_log(path, topics=("/tf", "/edges"))
    tf = sorted(log["messages"].get("/tf", []), key=lambda m: m[0])
    ed = sorted(log["messages"].get("/edges", []), key=lambda m: m[0])
    if not tf or not ed:
        raise Se3SyncError(f"{path}: the log has no /tf or /edges messages to animate")
    meta = log["metadata"]
    N = int(meta.get("n_agents", len(tf[0][1]["transforms"])))
    ids = json.loads(meta["agent_ids"]) if "agent_ids" in meta else list(range(1, N + 1))
    index = {f"agent_{a}": i for i, a in enumerate(ids)}
    T = len(tf)
    p = np.zeros((T, N, 3))
    q = np.zeros((T, N, 4))
    q[..., 3] = 1.0
    for a, (_, m) in enumerate(tf):
        for x in m["transforms"]:
            i = index.get(x["child_frame_id"])
            if i is None:
                continue
            tr, ro = x["translation"], x["rotation"]
            p[a, i] = (tr["x"], tr["y"], tr["z"])
            q[a, i] = (ro["x"], ro["y"], ro["z"], ro["w"])
    edges = np.array(json.loads(meta.get("edges", "[]")), int).reshape(-1, 2)
    if "inertias" in meta and "masses" in meta:
        J = np.array(json.loads(meta["inertias"]), float)
        m = np.array(json.loads(meta["masses"]), float)
        box = np.array([box_size(J[i], m[i]) for i in range(N)])
    else:  # logs written before the inertias were logged
        box = np.full((N, 3), 0.3)
    rot = np.array([[e["rot_err"] if e["rot_err"] is not None else np.nan for e in m[1]["edges"]]
                    for m in ed], float)
    return {"t": np.array([m[0] for m in tf]) * 1e-9, "p": p, "R": quat_to_rot(np.asarray(q, float)[..., [3, 0, 1, 2]]),
            "t_e": np.array([m[0] for m in ed]) * 1e-9, "rot_err": rot, "edges": edges,
            "box": box, "ids": ids, "name": meta.get("scenario_name", Path(path).stem),
            "controller": meta.get("controller", "")}


def _writer(out: Path, fps: float):
    """A matplotlib writer for the suffix: .gif via Pillow (or ffmpeg), .mp4 via ffmpeg."""
    from matplotlib import animation

    suffix = out.suffix.lower()
    ff = animation.writers.is_available("ffmpeg")
    if suffix == ".gif":
        try:
            import PIL  # noqa: F401
            return animation.PillowWriter(fps=fps)
        except ImportError:
            if ff:
                return animation.FFMpegWriter(fps=fps)
            raise Se3SyncError("-o: writing a GIF needs Pillow (pip install pillow) or ffmpeg "
                               "(e.g. apt-get install ffmpeg)") from None
    if suffix == ".mp4":
        if not ff:
            raise Se3SyncError("-o: writing an MP4 needs ffmpeg on PATH (e.g. apt-get install "
                               "ffmpeg); or write a .gif (Pillow)")
        return animation.FFMpegWriter(fps=fps, codec="h264", extra_args=["-pix_fmt", "yuv420p"])
    raise Se3SyncError(f"-o: the suffix must be .mp4 or .gif, got {out.suffix or 'none'!r}")


# body colours: one per agent (matplotlib's tab10, cycled), so that bodies stay apart
_BODY_ALPHA = 0.45
# bodies closer than this fraction of the largest box are drawn as one cluster: nested boxes
# (each smaller than the one before) under one label naming them all
_SAME_PLACE = 1e-3
_NEST = 0.22


def clusters(p, tol) -> list:
    """Groups of agent indices whose positions lie within ``tol`` of the group's first (in
    index order): [[0, 2, 4], [1, 3, 5]] for the paper's start, where the odd and the even
    agents coincide."""
    left = list(range(len(p)))
    out = []
    while left:
        i = left.pop(0)
        near = [j for j in left if np.linalg.norm(p[j] - p[i]) <= tol]
        left = [j for j in left if j not in near]
        out.append([i] + near)
    return out


def nest_scales(groups, n) -> np.ndarray:
    """The size factor of each body: 1 for the first of a cluster, then smaller by _NEST for
    each next one (at least 0.3), so that bodies at one place show as nested boxes."""
    scale = np.ones(n)
    for g in groups:
        for k, i in enumerate(g):
            scale[i] = max(0.3, 1.0 - _NEST * k)
    return scale


def _figure(d, times, idx, idx_e):
    """The figure and its ``draw(frame)``: bodies (boxes of their inertia, one colour per
    agent, nested where they coincide), body axes, edges coloured by their error, one number
    label per place, a colour bar of the edge colours, the time and the max error."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import ListedColormap, LogNorm
    from mpl_toolkits.mplot3d.art3d import Line3DCollection, Poly3DCollection

    P, R = d["p"], d["R"]
    N = P.shape[1]
    corners = _CORNERS[None, :, :] * d["box"][:, None, :]  # (N, 8, 3) in the body frame
    fig = plt.figure(figsize=(7.2, 6.0))
    ax = fig.add_axes([0.0, 0.02, 0.8, 0.9], projection="3d")
    sel = P[idx]
    lo, hi = sel.reshape(-1, 3).min(0), sel.reshape(-1, 3).max(0)
    c, r = (lo + hi) / 2, max(float((hi - lo).max()) / 2, float(d["box"].max())) * 1.15
    ax.set_box_aspect((1, 1, 1))
    palette = plt.get_cmap("tab10").colors
    face = [(*palette[i % len(palette)], _BODY_ALPHA) for i in range(N)]
    bodies = Poly3DCollection([[(0, 0, 0), (0, 0, 0), (0, 0, 0)]], edgecolor="k", lw=0.3)
    ax.add_collection3d(bodies)
    axes_lines = Line3DCollection([[(0, 0, 0), (0, 0, 0)]], lw=1.5)
    ax.add_collection3d(axes_lines)
    edge_lines = Line3DCollection([[(0, 0, 0), (0, 0, 0)]], lw=2.5)
    ax.add_collection3d(edge_lines)
    # the collections start with a placeholder (mplot3d cannot add an empty one);
    # set the limits after adding them
    ax.set(xlim=(c[0] - r, c[0] + r), ylim=(c[1] - r, c[1] + r), zlim=(c[2] - r, c[2] + r),
           xlabel="x (m)", ylabel="y (m)", zlabel="z (m)")
    # one label per agent; a cluster's first agent carries the whole cluster's numbers
    labels = [ax.text(0, 0, 0, "", fontsize=9, fontweight="bold", ha="center", va="bottom",
                      zorder=10, bbox=dict(boxstyle="round,pad=0.2", fc="white", ec="0.3",
                                           lw=0.6, alpha=0.85)) for _ in range(N)]
    # the colour bar of the edges: the log scale of `error_color` sampled densely
    grid = np.geomspace(ERR_LO, ERR_HI, 256)
    sm = ScalarMappable(norm=LogNorm(ERR_LO, ERR_HI), cmap=ListedColormap(error_colors(grid)))
    cax = fig.add_axes([0.84, 0.2, 0.03, 0.6])
    cb = fig.colorbar(sm, cax=cax)
    cb.set_label(r"edge colour: $\|I-\bar R_k\|_F$")
    title = fig.suptitle("", fontsize=10, y=0.98)
    L = 0.75 * float(d["box"].max())
    tol = _SAME_PLACE * float(d["box"].max())
    ax_cols = [(1, .2, .2), (.2, .8, .2), (.2, .4, 1)] * N
    E = d["edges"] - 1

    def draw(f):
        a = idx[f]
        p, Rm = P[a], R[a]
        groups = clusters(p, tol)
        scale = nest_scales(groups, N)
        world = (np.einsum("nij,nkj->nki", Rm, corners * scale[:, None, None])
                 + p[:, None, :])
        bodies.set_verts([world[i][list(fc)] for i in range(N) for fc in _FACES])
        bodies.set_facecolor([face[i] for i in range(N) for _ in _FACES])
        axes_lines.set_segments([(p[i], p[i] + L * Rm[i][:, j]) for i in range(N)
                                 for j in range(3)])
        axes_lines.set_color(ax_cols)
        err = d["rot_err"][idx_e[f]]
        edge_lines.set_segments([(p[i], p[j]) for i, j in E])
        edge_lines.set_color([error_color(float(e)) for e in err])
        for lab in labels:
            lab.set_text("")
        for g in groups:
            lab = labels[g[0]]
            i = g[0]
            lab.set_text(" = ".join(str(d["ids"][j]) for j in g))
            lab.set_position((p[i, 0], p[i, 1]))
            lab.set_3d_properties(p[i, 2] + 0.6 * L, None)   # screen-aligned text
        title.set_text(f"{d['name']} {d['controller']}   t = {times[f]:7.3f} s   "
                       f"max ‖I − R̄_k‖_F = {np.nanmax(err) if len(err) else 0:.3g}")
        return bodies, axes_lines, edge_lines, title

    return fig, draw


def _frames(d, duration, fps, tmin, tmax):
    t = d["t"]
    t0 = t[0] if tmin is None else max(float(tmin), t[0])
    t1 = t[-1] if tmax is None else min(float(tmax), t[-1])
    if not t1 >= t0:
        raise Se3SyncError(f"--tmax: must be above --tmin and inside the log ({t[0]:g}..{t[-1]:g} s)")
    n_frames = max(1, int(round(duration * fps)))
    times = np.linspace(t0, t1, n_frames)
    idx = np.clip(np.searchsorted(t, times, side="right") - 1, 0, len(t) - 1)
    idx_e = np.clip(np.searchsorted(d["t_e"], times, side="right") - 1, 0, len(d["t_e"]) - 1)
    return times, idx, idx_e


def snapshot(path, out, t: float = 0.0, dpi: int = 100) -> Path:
    """One frame of the animation, the log's record at simulated time ``t`` (the latest at or
    before it), as a still image (format from the suffix, e.g. .png), written atomically."""
    import matplotlib.pyplot as plt

    d = load_poses(path)
    times, idx, idx_e = _frames(d, 1.0, 1.0, t, t)
    fig, draw = _figure(d, times, idx, idx_e)
    out = Path(out)
    try:
        draw(0)
        with atomic_path(out) as tmp, open(tmp, "wb") as f:
            fig.savefig(f, format=out.suffix.lstrip(".").lower() or "png", dpi=dpi)
    finally:
        plt.close(fig)
    return out


def animate_log(path, out, *, duration: float = 10.0, fps: float = 20.0, tmin=None, tmax=None,
                dpi: int = 100, progress: bool = False) -> int:
    """Renders round(duration·fps) frames spread uniformly over [tmin, tmax] of simulated time
    into ``out`` (atomically). Returns the number of frames."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib import animation

    if not duration > 0:
        raise Se3SyncError(f"--duration: must be > 0, got {duration:g}")
    if not fps > 0:
        raise Se3SyncError(f"--fps: must be > 0, got {fps:g}")
    out = Path(out)
    writer = _writer(out, fps)
    d = load_poses(path)
    times, idx, idx_e = _frames(d, duration, fps, tmin, tmax)
    n_frames = len(times)
    fig, draw = _figure(d, times, idx, idx_e)

    bar = None
    if progress:
        bar = tqdm(total=n_frames, unit="frame", desc=out.name, mininterval=0.5)
    anim = animation.FuncAnimation(fig, draw, frames=n_frames, blit=False, repeat=False)
    try:
        with atomic_path(out) as tmp:
            # the writer picks its container from the file name: keep the suffix on the temp file
            tmp_s = str(tmp) + out.suffix
            try:
                anim.save(tmp_s, writer=writer, dpi=dpi,
                          progress_callback=(lambda i, n: bar.update(1)) if bar else None)
                Path(tmp_s).replace(tmp)
            finally:
                Path(tmp_s).unlink(missing_ok=True)
    finally:
        plt.close(fig)
        if bar is not None:
            bar.close()
    return n_frames
