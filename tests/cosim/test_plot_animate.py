"""Issue 33 §4: the plot's overlay (no empty legend entries on log axes, the θ inset's title and
its first jumps inside it) and the animation (numbers on the bodies, bodies at one place told
apart, a colour bar of the edge colours)."""
from pathlib import Path

import numpy as np
import pytest

from cosim.log import animate as A
from cosim.log import foxglove as fg
from cosim.run import run_scenario
from cosim.scenario import load_scenario

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def logs(tmp_path_factory):
    d = tmp_path_factory.mktemp("plots")
    out = {}
    for kind in ("hybrid", "gradient"):
        sc = load_scenario(ROOT / "scenarios" / "obstruction_6uav.toml", duration=0.5)
        out[kind] = d / f"{kind}.mcap"
        run_scenario(sc, controller=kind, log_path=out[kind])
    sc = load_scenario(ROOT / "scenarios" / "paper_6uav.toml", duration=0.05)
    out["paper"] = d / "paper.mcap"
    run_scenario(sc, log_path=out["paper"])
    return out


def test_overlay_has_no_empty_legend_entry_on_log_axes(logs):
    """The gradient baseline never moves from the critical point: its ω and v are exactly 0,
    which a log axis cannot draw. Each such curve has no legend entry of its own; one entry
    per axes names them as ≡ 0. Every other entry's curve has something to show."""
    import matplotlib.pyplot as plt

    from cosim.log.plot import make_figure

    fig = make_figure([logs["hybrid"], logs["gradient"]], ["hybrid", "gradient"])
    try:
        axes = {a.get_ylabel(): a for a in fig.axes if a.get_ylabel()}
        for ylabel, a in axes.items():
            if a.get_yscale() != "log":
                continue
            leg = a.get_legend()
            names = [t.get_text() for t in leg.get_texts()]
            lines = {ln.get_label(): ln for ln in a.get_lines()}
            for name in names:
                if "≡ 0" in name:
                    continue
                y = np.asarray(lines[name].get_ydata(), float)
                assert np.isfinite(y).any() and (y[np.isfinite(y)] > 0).any(), (ylabel, name)
        for key in (r"$\|\omega_i\|$ (rad/s)", r"$\|v_i\|$ (m/s)"):
            names = [t.get_text() for t in axes[key].get_legend().get_texts()]
            assert not any(n.startswith("gradient: i=") and "≡ 0" not in n for n in names)
            zero = [n for n in names if "≡ 0" in n]
            assert zero == ["gradient: i=1…i=6 ≡ 0 (not on the log axis)"]
            assert sum(n.startswith("hybrid: i=") for n in names) == 6
    finally:
        plt.close(fig)


def test_theta_inset_shows_its_title_and_the_first_jumps_inside(logs):
    import matplotlib.pyplot as plt

    from cosim.log.plot import make_figure

    fig = make_figure([logs["hybrid"]])
    try:
        ax_th = [a for a in fig.axes if "theta" in a.get_ylabel()][0]
        (ins,) = ax_th.child_axes
        lo, hi = ins.get_xlim()
        assert lo < 0.0 < hi   # the jumps at t = 0 are inside the frame, not on it
        assert ins.get_title() == ""
        (title,) = [t for t in ins.texts if t.get_text().startswith("first ")]
        # drawn inside the inset's own axes box
        fig.canvas.draw()
        bb, box = title.get_window_extent(), ins.get_window_extent()
        assert box.x0 <= bb.x0 and bb.x1 <= box.x1 and box.y0 <= bb.y0 and bb.y1 <= box.y1
    finally:
        plt.close(fig)


def test_clusters_of_the_papers_start():
    """The paper's start: p_i(0) = (I − R_i(0)) b/d with one rotation for the odd agents and
    one for the even ones, so 1, 3, 5 and 2, 4, 6 are each at one place."""
    sc = load_scenario(ROOT / "scenarios" / "paper_6uav.toml")
    p = sc.S0[:, 0:3]
    assert A.clusters(p, 1e-9) == [[0, 2, 4], [1, 3, 5]]
    assert A.clusters(p + np.arange(6)[:, None], 1e-9) == [[i] for i in range(6)]


def test_animation_frame_numbers_nests_and_colour_bar(logs, tmp_path):
    import matplotlib.pyplot as plt

    d = A.load_poses(logs["paper"])
    times, idx, idx_e = A._frames(d, 1.0, 1.0, 0.0, 0.0)
    fig, draw = A._figure(d, times, idx, idx_e)
    try:
        draw(0)
        ax = fig.axes[0]
        texts = sorted(t.get_text() for t in ax.texts if t.get_text())
        assert texts == ["1 = 3 = 5", "2 = 4 = 6"]
        # the coincident bodies are nested boxes of different sizes and colours
        bodies = ax.collections[0]
        size = A.nest_scales(A.clusters(d["p"][0], 1e-6), 6)
        assert size[0] > size[2] > size[4] and size[1] > size[3] > size[5]
        faces = bodies.get_facecolor()
        assert len({tuple(np.round(c, 6)) for c in faces}) == 6   # one colour per agent
        # the colour bar: the edges' scale, green at ERR_LO to red at ERR_HI, log
        cb_ax = fig.axes[1]
        from matplotlib.colors import LogNorm

        (im,) = [c for c in cb_ax.collections if isinstance(getattr(c, "norm", None), LogNorm)]
        norm, cmap = im.norm, im.cmap
        assert (norm.vmin, norm.vmax) == (fg.ERR_LO, fg.ERR_HI)
        assert np.allclose(cmap(0.0)[:3], fg.error_color(fg.ERR_LO), atol=1e-2)
        assert np.allclose(cmap(1.0)[:3], fg.error_color(fg.ERR_HI), atol=1e-2)
        mid = float(np.sqrt(fg.ERR_LO * fg.ERR_HI))
        assert np.allclose(cmap(norm(mid))[:3], fg.error_color(mid), atol=1e-2)
    finally:
        plt.close(fig)
    out = A.snapshot(logs["paper"], tmp_path / "frame.png", t=0.0, dpi=50)
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
