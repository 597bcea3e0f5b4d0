"""Issue 10: Foxglove 3D messages, plots, animation and the obstruction scenario."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from controller import se3
from cosim.log import foxglove as fg
from cosim.run import run_scenario
from cosim.log.reader import read_log
from cosim.scenario import load_scenario

ROOT = Path(__file__).resolve().parents[2]
SCHEMAS = Path(__file__).parents[1] / "data" / "foxglove_schemas"
OBSTRUCTION = ROOT / "scenarios" / "obstruction_6uav.toml"


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """The obstruction scenario over 20 s (50,000 steps at h = 0.4 ms), hybrid and gradient."""
    d = tmp_path_factory.mktemp("see")
    out = {}
    for kind in ("hybrid", "gradient"):
        sc = load_scenario(OBSTRUCTION, duration=20.0)
        log = d / f"{kind}.mcap"
        summary = run_scenario(sc, controller=kind, log_path=log)
        out[kind] = (log, summary, sc)
    return out


def _validator(name):
    jsonschema = pytest.importorskip("jsonschema")
    schema = json.loads((SCHEMAS / f"{name}.json").read_text())
    cls = jsonschema.validators.validator_for(schema)
    cls.check_schema(schema)
    return cls(schema)


def test_messages_validate_against_foxglove_schemas(runs):
    log = read_log(runs["hybrid"][0])
    msgs = log["messages"]
    for topic, name in [("/scene", "SceneUpdate"), ("/tf", "FrameTransforms")] + \
            [(f"/trail/agent_{i}", "PosesInFrame") for i in range(1, 7)]:
        v = _validator(name)
        assert msgs[topic], topic
        for _, m in msgs[topic][:: max(1, len(msgs[topic]) // 40)] + msgs[topic][-1:]:
            errors = list(v.iter_errors(m))
            assert not errors, (topic, errors[0].message)


def test_channels_carry_foxglove_schema_names_and_content(runs):
    from mcap.reader import make_reader

    with open(runs["hybrid"][0], "rb") as f:
        summ = make_reader(f).get_summary()
    by_topic = {c.topic: summ.schemas[c.schema_id] for c in summ.channels.values()}
    for topic, name in (("/scene", "SceneUpdate"), ("/tf", "FrameTransforms"),
                        ("/trail/agent_3", "PosesInFrame")):
        s = by_topic[topic]
        assert s.name == f"foxglove.{name}" and s.encoding == "jsonschema"
        assert json.loads(s.data) == json.loads((SCHEMAS / f"{name}.json").read_text())


def test_scene_entities_and_edge_lines_match_poses(runs):
    log_path, _, sc = runs["hybrid"]
    log = read_log(log_path)
    tf = dict(log["messages"]["/tf"])
    edges_msgs = dict(log["messages"]["/edges"])
    scenes = log["messages"]["/scene"]
    # 20 Hz of 20 s, first at t = 0
    assert abs(len(scenes) - 400) <= 1
    edge_list = [tuple(e) for e in sc.graph.edge_list]
    for t_ns, m in scenes[::37]:
        ents = {e["id"]: e for e in m["entities"]}
        assert sorted(ents) == sorted([f"agent_{i}" for i in range(1, 7)] +
                                      [f"edge_{k}" for k in range(1, 6)])
        pos = {x["child_frame_id"]: np.array([x["translation"][c] for c in "xyz"])
               for x in tf[t_ns]["transforms"]}
        for i in range(1, 7):
            a = ents[f"agent_{i}"]
            assert a["frame_id"] == f"agent_{i}" and a["frame_locked"]
            size = a["cubes"][0]["size"]
            # the box of agent i has its inertia: J = m/12 diag(b²+c², a²+c², a²+b²)
            A, B, C = size["x"], size["y"], size["z"]
            J = sc.masses[i - 1] / 12 * np.array([B * B + C * C, A * A + C * C, A * A + B * B])
            np.testing.assert_allclose(J, np.diag(sc.inertias[i - 1]), rtol=1e-12)
            assert len(a["arrows"]) == 3
        errs = [e["rot_err"] for e in edges_msgs[t_ns]["edges"]]
        for k, (i, j) in enumerate(edge_list, start=1):
            e = ents[f"edge_{k}"]
            assert e["frame_id"] == "world" and len(e["lines"]) == 1
            pts = e["lines"][0]["points"]
            np.testing.assert_array_equal([pts[0][c] for c in "xyz"], pos[f"agent_{i}"])
            np.testing.assert_array_equal([pts[1][c] for c in "xyz"], pos[f"agent_{j}"])
            if not e["texts"]:  # not jumping: the colour is the error's
                col = e["lines"][0]["color"]
                x = min(1.0, max(0.0, math.log10(errs[k - 1] / 1e-4) / math.log10(2 * math.sqrt(2) / 1e-4)))
                assert (col["r"], col["g"]) == pytest.approx((x, 1 - x), abs=1e-12)


def test_edge_colour_follows_error():
    errs = [1e-6, 1e-4, 1e-3, 1e-2, 0.1, 1.0, 2 * math.sqrt(2)]
    cols = [fg.error_color(e) for e in errs]
    r = [c[0] for c in cols]
    g = [c[1] for c in cols]
    assert r[0] == 0.0 and r[-1] == pytest.approx(1.0) and g[0] == 1.0
    assert all(b > a for a, b in zip(r[1:], r[2:])) and all(b < a for a, b in zip(g[1:], g[2:]))


def test_jumping_edges_are_marked(runs):
    log = read_log(runs["hybrid"][0])
    jumps = log["messages"]["/jumps"]
    assert jumps and jumps[0][1]["t"] == 0.0
    first = log["messages"]["/scene"][0][1]
    marked = {e["id"] for e in first["entities"] if e["texts"]}
    jumped0 = {f"edge_{m['edge']}" for t, m in jumps if t == 0}
    assert jumped0 and jumped0 <= marked
    last = log["messages"]["/scene"][-1][1]
    assert not any(e["texts"] for e in last["entities"])


def test_trails_are_recent_poses(runs):
    log = read_log(runs["hybrid"][0])
    tf = log["messages"]["/tf"]
    trail = log["messages"]["/trail/agent_4"]
    t_ns, m = trail[-1]
    # 5 s of poses kept at 5 Hz, and the current one when it is not kept
    assert len(m["poses"]) in (25, 26)
    tf_at = dict(tf)
    last = [x for x in tf_at[t_ns]["transforms"] if x["child_frame_id"] == "agent_4"][0]
    assert m["poses"][-1]["position"] == last["translation"]
    assert m["poses"][-1]["orientation"] == last["rotation"]


def test_layout_written_beside_and_attached(runs):
    log_path = runs["hybrid"][0]
    beside = json.loads(log_path.with_name("hybrid.layout.json").read_text())
    attached = json.loads(read_log(log_path)["attachments"]["foxglove_layout.json"])
    assert beside == attached
    cfg = beside["configById"]
    three = [k for k in cfg if k.startswith("3D!")]
    assert len(three) == 1 and cfg[three[0]]["followTf"] == "world"
    assert "/scene" in cfg[three[0]]["topics"]
    plotted = {p["value"] for k, c in cfg.items() if k.startswith("Plot!") for p in c["paths"]}
    assert {f"/edges.edges[{k}].rot_err" for k in range(5)} <= plotted
    assert {f"/edges.edges[{k}].theta" for k in range(5)} <= plotted and "/lyapunov.V" in plotted

    def leaves(node):
        return [node] if isinstance(node, str) else leaves(node["first"]) + leaves(node["second"])
    assert sorted(leaves(beside["layout"])) == sorted(cfg)


def test_obstruction_gradient_stuck_hybrid_converges(runs):
    _, hyb, sc = runs["hybrid"]
    _, grad, _ = runs["gradient"]
    # the initial state is exactly critical: R̄_k = R_a(π, v) with v an eigenvector of W
    w = sc.weighting
    for k, (i, j) in enumerate(sc.graph.edges):
        Xi, Xj = se3.T(sc.S0[i, 3:12].reshape(3, 3), sc.S0[i, :3]), \
            se3.T(sc.S0[j, 3:12].reshape(3, 3), sc.S0[j, :3])
        Xb = se3.inverse(Xj) @ Xi
        Rb = Xb[:3, :3]
        v = np.sqrt(np.clip((np.diag(Rb) + 1) / 2, 0, None))
        np.testing.assert_allclose(Rb, 2 * np.outer(v, v) - np.eye(3), atol=0)
        np.testing.assert_allclose(w.W @ v, (v @ w.W @ v) * v, atol=1e-15)
        np.testing.assert_allclose(Xb[:3, 3], (np.eye(3) - Rb) @ (w.b / w.d), atol=0)
    g0, g1 = grad["samples"][0]["rot_err"], grad["final"]["rot_err"]
    assert g0 == pytest.approx(2 * math.sqrt(2))
    assert abs(g1 - g0) <= 0.01 * g0
    assert grad["n_jumps"] == 0
    assert hyb["final"]["rot_err"] < 1e-2
    assert any(j["t"] == 0.0 for j in hyb["jumps"])


def test_plot_has_log_axes_and_V_panel(runs, tmp_path):
    import matplotlib.pyplot as plt

    from cosim.log.plot import make_figure

    fig = make_figure([runs["hybrid"][0], runs["gradient"][0]], ["hybrid", "gradient"])
    try:
        axes = [a for a in fig.axes if a.get_ylabel()]
        ylabels = [a.get_ylabel() for a in axes]
        assert r"$\bar V$" in ylabels
        for a in axes:
            want = "linear" if "theta" in a.get_ylabel() else "log"
            assert a.get_yscale() == want, a.get_ylabel()
        ax_V = axes[ylabels.index(r"$\bar V$")]
        assert {l.get_label() for l in ax_V.get_lines()} == {"hybrid", "gradient"}
        # edges of one run differ in dash pattern, not only in colour
        ax_R = axes[0]
        hyb = [l for l in ax_R.get_lines() if l.get_label().startswith("hybrid")]
        assert len(hyb) == 5 and len({str(l._unscaled_dash_pattern) for l in hyb}) == 5
        # every jump of the hybrid run is a marker on the θ axes
        ax_th = axes[-1]
        n_marks = sum(len(l.get_xdata()) for l in ax_th.get_lines()
                      if l.get_label().startswith("hybrid: jump"))
        assert n_marks == runs["hybrid"][1]["n_jumps"]
        # the inset zooms on the first jumps
        inset = ax_th.child_axes
        assert len(inset) == 1 and inset[0].get_xlim()[1] <= 1.5
    finally:
        plt.close(fig)
    fig = make_figure([runs["hybrid"][0]], linear=True, tmin=1.0, tmax=5.0)
    try:
        assert all(a.get_yscale() == "linear" for a in fig.axes)
        assert fig.axes[0].get_xlim() == (1.0, 5.0)
    finally:
        plt.close(fig)


def test_plot_cli_overlay(runs, tmp_path):
    from cosim.cli import main

    out = tmp_path / "cmp.svg"
    assert main(["plot", str(runs["hybrid"][0]), str(runs["gradient"][0]), "--labels",
                 "hybrid,gradient", "-o", str(out), "--dpi", "80"]) == 0
    assert out.read_text().lstrip().startswith("<?xml")
    assert main(["plot", str(runs["hybrid"][0]), "--labels", "a,b", "-o",
                 str(tmp_path / "x.png")]) == 2
    assert not (tmp_path / "x.png").exists()


def test_animate_gif_frames(runs, tmp_path):
    from PIL import Image

    from cosim.cli import main

    out = tmp_path / "swarm.gif"
    assert main(["animate", str(runs["hybrid"][0]), "-o", str(out), "--duration", "1.5",
                 "--fps", "4", "--dpi", "40"]) == 0
    with Image.open(out) as im:
        assert im.n_frames == 6
    assert main(["animate", str(runs["hybrid"][0]), "-o", str(tmp_path / "x.avi")]) == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["swarm.gif"]


def test_animate_mp4_without_ffmpeg_names_it(runs, tmp_path, monkeypatch, capsys):
    from matplotlib import animation

    from cosim.cli import main

    monkeypatch.setattr(animation.writers, "is_available", lambda name: False)
    out = tmp_path / "swarm.mp4"
    assert main(["animate", str(runs["hybrid"][0]), "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "ffmpeg" in err[0] and not out.exists()


def test_scene_and_trails_carry_the_exact_values_and_zero_for_non_finite():
    """SceneBuilder's two encoders (templates when every value is finite, per value otherwise):
    the decoded lines and poses are the input floats exactly, the colours `error_colors`' (of
    the same error vector: the one computation the CDR scene encodes too), and
    a non-finite coordinate is written as 0.0 (JSON has no NaN) without touching the others."""
    rng = np.random.default_rng(5)
    N = 30
    edges = [(i + 1, int(rng.integers(1, i + 1))) for i in range(1, N)]
    J, m = np.tile(np.diag([0.04, 0.05, 0.08]), (N, 1, 1)), np.ones(N)
    b = fg.SceneBuilder(edges, J, m, trail_len=3)
    for k, bad in enumerate((False, False, True, False)):
        S = rng.standard_normal((N, 18)) * 10.0 ** rng.integers(-6, 6, (N, 1))
        q = rng.standard_normal((N, 4))
        if bad:
            S[3, 1] = np.nan
            q[7, 2] = np.inf
        err = np.abs(rng.standard_normal(N - 1)) * 10.0 ** rng.integers(-12, 1, N - 1)
        jump = rng.random(N - 1) < 0.2
        ts = f'{{"sec":{k},"nsec":0}}'
        P = np.where(np.isfinite(S[:, :3]), S[:, :3], 0.0)
        Q = np.where(np.isfinite(q), q, 0.0)
        scene = json.loads(b.scene(ts, S, err, jump))
        lines = {e["id"]: e["lines"][0] for e in scene["entities"] if e["id"].startswith("edge_")}
        assert len(lines) == N - 1
        for kk, (i, j) in enumerate(edges):
            ln = lines[f"edge_{kk + 1}"]
            pts = [[p["x"], p["y"], p["z"]] for p in ln["points"]]
            assert pts == [P[i - 1].tolist(), P[j - 1].tolist()]
            rgb = (1.0, 1.0, 1.0) if jump[kk] else tuple(fg.error_colors(err)[kk].tolist())
            assert (ln["color"]["r"], ln["color"]["g"], ln["color"]["b"]) == rgb
        trails = [json.loads(t) for t in b.trails(ts, S, q)]
        for i, tr in enumerate(trails):
            cur = tr["poses"][-1]
            assert [cur["position"][a] for a in "xyz"] == P[i].tolist()
            assert [cur["orientation"][a] for a in "xyzw"] == Q[i].tolist()
