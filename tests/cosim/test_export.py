"""`se3sync export`: what every format holds equals what `read_log` reads from the log (JSON and
CDR logs), read back by each format's own reader; windows, decimation, channels, units; errors
and interruptions leave no file."""
import csv
import json

import numpy as np
import pytest

from cosim.cli import main
from cosim.log import export as E
from cosim.log.reader import read_log
from cosim.run import run_scenario
from cosim.scenario import load_scenario

from test_cosim_log import PAPER

OBSTRUCTION = PAPER.parent / "obstruction_6uav.toml"


@pytest.fixture(scope="module", params=["json", "cdr"])
def log(request, tmp_path_factory):
    """0.3 s of the obstruction scenario (28 jumps, most at t = 0) logged at 100 Hz."""
    d = tmp_path_factory.mktemp(f"export_{request.param}")
    sc = load_scenario(OBSTRUCTION, ["simulation.duration=0.3"])
    path = d / "run.mcap"
    run_scenario(sc, log_path=path, log_encoding=request.param)
    return path


def reference(path):
    """The log's values, taken from read_log's messages one by one (independently of the
    exporter's vectorised extraction)."""
    msgs = read_log(path)["messages"]
    ref = {}
    for t_ns, m in msgs["/edges"]:
        for e in m["edges"]:
            for q in ("theta", "mu_U", "rot_err", "pos_err", "U"):
                ref[(t_ns, f"edge{e['edge']}.{q}")] = e[q]
            ref[(t_ns, f"edge{e['edge']}.jump")] = 1.0 if e["mode"] == "jump" else 0.0
    for t_ns, m in msgs["/tf"]:
        for x in m["transforms"]:
            i = x["child_frame_id"].split("_")[1]
            for c in "xyz":
                ref[(t_ns, f"agent{i}.p_{c}")] = x["translation"][c]
            for c in "xyzw":
                ref[(t_ns, f"agent{i}.q_{c}")] = x["rotation"][c]
    for t_ns, m in msgs["/agents"]:
        for a in m["agents"]:
            for q in ("omega", "v", "torque", "force"):
                for c, val in zip("xyz", a[q]):
                    ref[(t_ns, f"agent{a['agent']}.{q}_{c}")] = val
    for t_ns, m in msgs["/lyapunov"]:
        ref[(t_ns, "V")] = m["V"]
        ref[(t_ns, "kX_U")] = m["kX_U"]
    times = sorted({t for t, _ in msgs["/edges"]})
    jumps = [m for _, m in msgs["/jumps"]]
    return ref, times, jumps


def read_csv(path):
    with open(path, newline="") as f:
        lines = f.read().splitlines()
    assert lines[0].startswith("# se3sync export of ")
    assert lines[1].startswith("# units: ")
    units = lines[1][len("# units: "):].split(",")
    rows = list(csv.reader(lines[2:]))
    names = rows[0]
    assert len(units) == len(names)
    cols = {n: [float(r[k]) for r in rows[1:]] for k, n in enumerate(names)}
    return cols, dict(zip(names, units))


def read_parquet(path):
    import pyarrow.parquet as pq

    tb = pq.read_table(path)
    units = {f.name: f.metadata[b"unit"].decode() for f in tb.schema}
    assert json.loads(tb.schema.metadata[b"se3sync"])["scenario_name"] == "obstruction_6uav"
    return {n: tb.column(n).to_numpy().tolist() for n in tb.column_names}, units


def flat_from_groups(get, t, edge_ids, agent_ids, units_of):
    """Flat column names from the grouped arrays of .npz/.mat (an independent flattening)."""
    cols = {"t": list(np.ravel(t))}
    units = {"t": units_of("t")}
    for q in ("theta", "mu_U", "rot_err", "pos_err", "U", "jump"):
        a = np.atleast_2d(get("edges", q))
        for j, k in enumerate(edge_ids):
            cols[f"edge{k}.{q}"] = a[:, j].tolist()
            units[f"edge{k}.{q}"] = units_of(f"edges.{q}")
    for grp, qs in (("tf", (("p", "xyz"), ("q", "xyzw"))),
                    ("agents", (("omega", "xyz"), ("v", "xyz"), ("torque", "xyz"),
                                ("force", "xyz")))):
        for q, comps in qs:
            a = get(grp, q)
            for j, i in enumerate(agent_ids):
                for c, comp in enumerate(comps):
                    cols[f"agent{i}.{q}_{comp}"] = a[:, j, c].tolist()
                    units[f"agent{i}.{q}_{comp}"] = units_of(f"{grp}.{q}")
    for q in ("V", "kX_U"):
        cols[q] = list(np.ravel(get("lyapunov", q)))
        units[q] = units_of(f"lyapunov.{q}")
    jumps = {q: list(np.ravel(get("jumps", q))) for q in
             ("t", "edge", "theta_before", "theta_after", "mu")}
    return cols, units, jumps


def read_npz(path):
    z = np.load(path)   # no pickle: every entry is a plain array or a string array
    units = json.loads(str(z["units"]))
    assert json.loads(str(z["metadata"]))["scenario_name"] == "obstruction_6uav"
    return flat_from_groups(lambda g, q: z[f"{g}.{q}"], z["t"], z["edge_ids"].tolist(),
                            z["agent_ids"].tolist(), lambda n: units[n])


def read_mat(path):
    import scipy.io

    m = scipy.io.loadmat(path, simplify_cells=True)
    assert m["metadata"]["scenario_name"] == "obstruction_6uav"
    assert m["units"]["t"] == "s"
    return flat_from_groups(lambda g, q: np.asarray(m[g][q]), m["t"],
                            np.atleast_1d(m["edge_ids"]).tolist(),
                            np.atleast_1d(m["agent_ids"]).tolist(),
                            lambda n: m["units"][n] if n == "t" else
                            m["units"][n.split(".")[0]][n.split(".")[1]])


EXPECTED_UNITS = {"theta": "rad", "pos_err": "m", "p": "m", "omega": "rad/s", "v": "m/s",
                  "torque": "N m", "force": "N", "V": "J", "rot_err": "1"}


def check_against_log(cols, units, jumps, ref, times, ref_jumps, sel=None):
    sel = times if sel is None else sel
    assert cols["t"] == [t * 1e-9 for t in sel]
    names = {n for (_, n) in ref}
    assert set(cols) == names | {"t"}
    for n in names:
        want = [ref[(t, n)] for t in sel]
        assert cols[n] == want, n   # the same floats, bit for bit
    for n, u in units.items():
        q = n.split(".")[-1].rsplit("_", 1)[0] if n.startswith("agent") else n.split(".")[-1]
        if q in EXPECTED_UNITS:
            assert u == EXPECTED_UNITS[q], (n, u)
    assert units["t"] == "s"
    for q in ("t", "edge", "theta_before", "theta_after", "mu"):
        assert list(jumps[q]) == [j[q] for j in ref_jumps], q


@pytest.mark.parametrize("fmt", [".csv", ".parquet", ".npz", ".mat"])
def test_export_equals_read_log(log, tmp_path, fmt):
    ref, times, ref_jumps = reference(log)
    assert len(times) == 30 and len(ref_jumps) >= 15 and ref_jumps[0]["t"] == 0.0
    out = tmp_path / f"out{fmt}"
    assert main([ "export", str(log), "-o", str(out)]) == 0
    if fmt == ".csv":
        cols, units = read_csv(out)
        jc, _ = read_csv(E.jumps_path(out))
        jumps = {q: [int(x) for x in v] if q == "edge" else v for q, v in jc.items()}
    elif fmt == ".parquet":
        cols, units = read_parquet(out)
        jumps, ju = read_parquet(E.jumps_path(out))
        assert ju == {"t": "s", "edge": "1", "theta_before": "rad", "theta_after": "rad",
                      "mu": "1"}
    elif fmt == ".npz":
        cols, units, jumps = read_npz(out)
    else:
        cols, units, jumps = read_mat(out)
    check_against_log(cols, units, jumps, ref, times, ref_jumps)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        [out.name] + ([E.jumps_path(out).name] if fmt in (".csv", ".parquet") else []))


def test_window_decimation_and_channels(log, tmp_path):
    ref, times, ref_jumps = reference(log)
    out = tmp_path / "w.csv"
    assert main(["export", str(log), "-o", str(out), "--tmin", "0.05", "--tmax", "0.25",
                 "--every", "3", "--channels", "edges,/lyapunov,jumps"]) == 0
    cols, units = read_csv(out)
    sel = [t for t in times if 0.05 <= t * 1e-9 <= 0.25][::3]
    assert cols["t"] == [t * 1e-9 for t in sel] and len(sel) == 7
    assert not any(n.startswith("agent") for n in cols)
    for n in cols:
        if n != "t":
            assert cols[n] == [ref[(t, n)] for t in sel], n
    jc, _ = read_csv(E.jumps_path(out))
    assert jc["t"] == [j["t"] for j in ref_jumps if 0.05 <= j["t"] <= 0.25]
    # JSON and CDR logs of the same run export the same numbers (the same floats logged)
    ex = E.load_export(log, "edges,tf,agents,lyapunov")
    assert ex.series["edges.theta"].shape == (30, 5) and ex.series["tf.q"].shape == (30, 6, 4)


def test_json_and_cdr_logs_export_alike(tmp_path):
    sc = load_scenario(OBSTRUCTION, ["simulation.duration=0.05"])
    ex = []
    for enc in ("json", "cdr"):
        run_scenario(sc, log_path=tmp_path / f"{enc}.mcap", log_encoding=enc)
        ex.append(E.load_export(tmp_path / f"{enc}.mcap"))
    a, b = ex
    assert np.array_equal(a.t, b.t) and a.series.keys() == b.series.keys()
    for k in a.series:
        assert np.array_equal(a.series[k], b.series[k], equal_nan=True), k
    for k in a.jumps:
        assert np.array_equal(a.jumps[k], b.jumps[k]), k


@pytest.mark.parametrize("argv, words", [
    (["-o", "x.txt"], "--output"),
    (["-o", "x.csv", "--channels", "edges,nope"], "--channels: unknown channel 'nope'"),
    (["-o", "x.csv", "--every", "0"], "--every"),
    (["-o", "x.csv", "--tmin", "5"], "--tmin/--tmax"),
    (["-o", "x.csv", "--tmin", "0.2", "--tmax", "0.1"], "--tmax"),
    (["-o", "x.csv", "--channels", "/link/stats"], "--channels"),
    (["-o", "nodir/x.csv"], "--output"),
])
def test_bad_requests_are_one_line_and_write_nothing(log, tmp_path, monkeypatch, capsys, argv,
                                                     words):
    monkeypatch.chdir(tmp_path)
    assert main(["export", str(log)] + argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("se3sync export: error: ") and "\n" not in err and words in err
    assert list(tmp_path.iterdir()) == []


def test_not_a_log_is_one_line(tmp_path, capsys):
    bad = tmp_path / "x.mcap"
    bad.write_bytes(b"not an mcap file at all")
    assert main(["export", str(bad), "-o", str(tmp_path / "x.npz")]) == 2
    assert "not a readable MCAP" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.mcap"]


def test_missing_pyarrow_names_the_extra(log, tmp_path, monkeypatch, capsys):
    import sys

    monkeypatch.setitem(sys.modules, "pyarrow", None)   # import pyarrow → ModuleNotFoundError
    assert main(["export", str(log), "-o", str(tmp_path / "x.parquet")]) == 2
    err = capsys.readouterr().err
    assert "'sweep' extra" in err and err.count("\n") == 1
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("fmt, victim", [(".csv", "_csv_table"), (".npz", "savez_compressed"),
                                         (".mat", "savemat")])
def test_interrupted_export_leaves_no_file(log, tmp_path, monkeypatch, fmt, victim):
    """Ctrl-C (KeyboardInterrupt, what `se3sync` turns SIGINT and SIGTERM into) in the middle
    of writing: neither the file nor its temporary is left, nor a CSV's jumps file."""
    out = tmp_path / f"x{fmt}"
    out.write_text("the previous export")
    calls = []

    def boom(*a, **k):
        calls.append(1)
        if fmt != ".csv" or len(calls) == 2:   # the CSV: while writing the second file
            raise KeyboardInterrupt
        return real(*a, **k)

    if victim == "_csv_table":
        real = E._csv_table
        monkeypatch.setattr(E, "_csv_table", boom)
    elif victim == "savez_compressed":
        real = np.savez_compressed
        monkeypatch.setattr(np, "savez_compressed", boom)
    else:
        import scipy.io
        real = scipy.io.savemat
        monkeypatch.setattr(scipy.io, "savemat", boom)
    with pytest.raises(KeyboardInterrupt):
        E.export_log(log, out)
    assert sorted(p.name for p in tmp_path.iterdir()) == [out.name]
    assert out.read_text() == "the previous export"
