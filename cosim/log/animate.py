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
from .foxglove import box_size, error_color
from .mcap import read_log

__all__ = ["load_poses", "animate_log"]

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


def animate_log(path, out, *, duration: float = 10.0, fps: float = 20.0, tmin=None, tmax=None,
                dpi: int = 100, progress: bool = False) -> int:
    """Renders round(duration·fps) frames spread uniformly over [tmin, tmax] of simulated time
    into ``out`` (atomically). Returns the number of frames."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib import animation
    from mpl_toolkits.mplot3d.art3d import Line3DCollection, Poly3DCollection


    if not duration > 0:
        raise Se3SyncError(f"--duration: must be > 0, got {duration:g}")
    if not fps > 0:
        raise Se3SyncError(f"--fps: must be > 0, got {fps:g}")
    out = Path(out)
    writer = _writer(out, fps)
    d = load_poses(path)
    t, P, R = d["t"], d["p"], d["R"]
    t0 = t[0] if tmin is None else max(float(tmin), t[0])
    t1 = t[-1] if tmax is None else min(float(tmax), t[-1])
    if not t1 >= t0:
        raise Se3SyncError(f"--tmax: must be above --tmin and inside the log ({t[0]:g}..{t[-1]:g} s)")
    n_frames = max(1, int(round(duration * fps)))
    times = np.linspace(t0, t1, n_frames)
    idx = np.clip(np.searchsorted(t, times, side="right") - 1, 0, len(t) - 1)
    idx_e = np.clip(np.searchsorted(d["t_e"], times, side="right") - 1, 0, len(d["t_e"]) - 1)
    N = P.shape[1]
    corners = _CORNERS[None, :, :] * d["box"][:, None, :]  # (N, 8, 3) in the body frame

    fig = plt.figure(figsize=(6.4, 6.0))
    ax = fig.add_subplot(projection="3d")
    sel = P[idx]
    lo, hi = sel.reshape(-1, 3).min(0), sel.reshape(-1, 3).max(0)
    c, r = (lo + hi) / 2, max(float((hi - lo).max()) / 2, float(d["box"].max())) * 1.15
    ax.set_box_aspect((1, 1, 1))
    bodies = Poly3DCollection([[(0, 0, 0), (0, 0, 0), (0, 0, 0)]], facecolor=(0.55, 0.6, 0.7, 0.6), edgecolor="k", lw=0.3)
    ax.add_collection3d(bodies)
    axes_lines = Line3DCollection([[(0, 0, 0), (0, 0, 0)]], lw=1.5)
    ax.add_collection3d(axes_lines)
    edge_lines = Line3DCollection([[(0, 0, 0), (0, 0, 0)]], lw=2.5)
    ax.add_collection3d(edge_lines)
    # the collections start with a placeholder (mplot3d cannot add an empty one);
    # set the limits after adding them
    ax.set(xlim=(c[0] - r, c[0] + r), ylim=(c[1] - r, c[1] + r), zlim=(c[2] - r, c[2] + r),
           xlabel="x (m)", ylabel="y (m)", zlabel="z (m)")
    labels = [ax.text(0, 0, 0, f"{d['ids'][i]}", fontsize=8) for i in range(N)]
    title = ax.set_title("")
    L = 0.75 * float(d["box"].max())
    ax_cols = [(1, .2, .2), (.2, .8, .2), (.2, .4, 1)] * N
    E = d["edges"] - 1

    def draw(f):
        a = idx[f]
        p, Rm = P[a], R[a]
        world = np.einsum("nij,nkj->nki", Rm, corners) + p[:, None, :]
        bodies.set_verts([world[i][list(face)] for i in range(N) for face in _FACES])
        axes_lines.set_segments([(p[i], p[i] + L * Rm[i][:, j]) for i in range(N) for j in range(3)])
        axes_lines.set_color(ax_cols)
        err = d["rot_err"][idx_e[f]]
        edge_lines.set_segments([(p[i], p[j]) for i, j in E])
        edge_lines.set_color([error_color(float(e)) for e in err])
        for i, lab in enumerate(labels):
            lab.set_position((p[i, 0], p[i, 1]))
            lab.set_3d_properties(p[i, 2] + 0.6 * L, "z")
        title.set_text(f"{d['name']} {d['controller']}   t = {times[f]:7.3f} s   "
                       f"max ‖I − R̄_k‖_F = {np.nanmax(err) if len(err) else 0:.3g}")
        return bodies, axes_lines, edge_lines, title

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
