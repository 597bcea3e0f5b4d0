"""Instances, FMU state and a second importer (libcosimpy) for the plant FMU."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from plant_fmu import build, layout
from plant_fmu.fast import FleetFMU, FMUError

N = 2  # bodies per instance in these tests

# one instance's run, also executed stand-alone in a subprocess
RUN_SCRIPT = textwrap.dedent("""
    import sys, numpy as np
    from plant_fmu.fast import FleetFMU

    def config(seed, n):
        rng = np.random.default_rng(seed)
        J = np.array([np.diag(rng.uniform(1.0, 1.4, 3)) + 0.05 * (np.ones((3, 3)) - np.eye(3)) for _ in range(n)])
        q0 = rng.normal(size=(n, 4))
        q0 /= np.linalg.norm(q0, axis=1, keepdims=True)
        return dict(mass=rng.uniform(0.5, 2.0, n), J=J, p0=rng.normal(size=(n, 3)), q0=q0,
                    xi0=rng.normal(size=(n, 6)), gravity=[0.0, 0.0, -9.81])

    def inputs(seed, n, k):
        return np.sin(np.arange(n * 6).reshape(n, 6) * (seed + 1) + 0.1 * k)

    def make(seed, n, path, name):
        f = FleetFMU(n, fmu_path=path, instance_name=name)
        f.set_parameters(**config(seed, n))
        f.initialize()
        return f

    if __name__ == "__main__":
        seed, n, path, steps = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3], int(sys.argv[4])
        f = make(seed, n, path, "solo")
        for k in range(steps):
            f.set_input(inputs(seed, n, k))
            f.do_step(k * 0.01, 0.01)
        sys.stdout.write(f.get_state().tobytes().hex())
        f.close()
""")

STEPS = 50


@pytest.fixture(scope="module")
def runner(tmp_path_factory):
    d = tmp_path_factory.mktemp("plant_run")
    script = d / "plant_run.py"
    script.write_text(RUN_SCRIPT)
    sys.path.insert(0, str(d))
    try:
        import plant_run  # noqa: F401
        yield script, sys.modules["plant_run"]
    finally:
        sys.path.remove(str(d))
        sys.modules.pop("plant_run", None)


@pytest.fixture(scope="module")
def fmu2():
    return build.fmu_path(N)


def test_six_instances_match_six_separate_processes(runner, fmu2):
    script, run = runner
    seeds = range(6)
    fleets = [run.make(s, N, fmu2, f"plant{s}") for s in seeds]
    try:
        for k in range(STEPS):  # interleaved, so any shared state would show
            for s, f in zip(seeds, fleets):
                f.set_input(run.inputs(s, N, k))
                f.do_step(k * 0.01, 0.01)
        together = [f.get_state().tobytes().hex() for f in fleets]
    finally:
        for f in fleets:
            f.close()
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(script.parent), os.getcwd(), env.get("PYTHONPATH", "")])
    procs = [subprocess.Popen([sys.executable, str(script), str(s), str(N), str(fmu2), str(STEPS)],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env) for s in seeds]
    for s, p in zip(seeds, procs):
        out, err = p.communicate(timeout=120)
        assert p.returncode == 0, err
        assert out == together[s], f"instance {s} differs from its separate run"
    assert len(set(together)) == 6  # the configurations really differ


def test_get_set_fmu_state_replays_bitwise(runner, fmu2):
    _, run = runner
    with run.make(3, N, fmu2, "a") as f:
        for k in range(10):
            f.set_input(run.inputs(3, N, k))
            f.do_step(k * 0.01, 0.01)
        state = f.get_fmu_state()

        def replay():
            for k in range(10, 20):
                f.set_input(run.inputs(3, N, k))
                f.do_step(k * 0.01, 0.01)
            return f.get_state().copy(), f.get_quat().copy()

        x1, q1 = replay()
        f.set_fmu_state(state)
        x2, q2 = replay()
        f.free_fmu_state(state)
        assert x1.tobytes() == x2.tobytes() and q1.tobytes() == q2.tobytes()
        assert not np.array_equal(x1, f.get_state() * 0)


def test_serialize_deserialize_replays_bitwise(runner, fmu2):
    _, run = runner
    with run.make(4, N, fmu2, "a") as f, FleetFMU(N, fmu_path=fmu2, instance_name="b") as g:
        for k in range(10):
            f.set_input(run.inputs(4, N, k))
            f.do_step(k * 0.01, 0.01)
        s = f.get_fmu_state()
        blob = f.serialize_fmu_state(s)
        f.free_fmu_state(s)
        for k in range(10, 15):
            f.set_input(run.inputs(4, N, k))
            f.do_step(k * 0.01, 0.01)
        expected = f.get_state().tobytes()
        # a fresh, never-initialised instance takes over the state
        s2 = g.deserialize_fmu_state(blob)
        g.set_fmu_state(s2)
        g.free_fmu_state(s2)
        for k in range(10, 15):
            g.set_input(run.inputs(4, N, k))
            g.do_step(k * 0.01, 0.01)
        assert g.get_state().tobytes() == expected
        # corrupted blobs are refused with a message
        for bad in (blob[:-1], b"X" + blob[1:]):
            with pytest.raises(FMUError, match="fmi2DeSerializeFMUstate"):
                g.deserialize_fmu_state(bad)
        # a state of a different FMU (other N) is refused
        with FleetFMU(1, fmu_path=build.fmu_path(1)) as h:
            h.initialize()
            s1 = h.get_fmu_state()
            blob1 = h.serialize_fmu_state(s1)
            h.free_fmu_state(s1)
        with pytest.raises(FMUError, match="bodies"):
            g.deserialize_fmu_state(blob1)


def test_reset_returns_to_start_values(fmu2):
    with FleetFMU(N, fmu_path=fmu2) as f:
        f.set_parameters(mass=[2.0, 3.0], xi0=np.ones((N, 6)))
        f.initialize()
        f.do_step(0.0, 0.1)
        f.reset()
        f.initialize()
        x = f.get_state()
        assert np.array_equal(x[:, 12:], np.zeros((N, 6)))  # xi0 back to its default 0
        assert np.array_equal(f.get_real(layout.vr_mass(N)), [1.0, 1.0])


LIBCOSIM_SCRIPT = textwrap.dedent("""
    import json, sys
    from libcosimpy.CosimExecution import CosimExecution
    from libcosimpy.CosimObserver import CosimObserver
    from libcosimpy.CosimSlave import CosimLocalSlave

    fmu, step_ns, steps, params, vrs = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), json.loads(sys.argv[4]), \\
        json.loads(sys.argv[5])
    ex = CosimExecution.from_step_size(step_ns)
    slave = CosimLocalSlave(fmu_path=fmu, instance_name="plant")
    if not slave.ptr():
        print("libcosim could not load the FMU", file=sys.stderr); sys.exit(3)
    idx = ex.add_local_slave(slave)
    if idx < 0:
        print("add_local_slave failed", file=sys.stderr); sys.exit(3)
    for vr, value in params:
        assert ex.real_initial_value(idx, vr, value), vr
    obs = CosimObserver.create_last_value()
    ex.add_observer(obs)
    assert ex.step(steps)
    print("RESULT " + json.dumps(obs.last_real_values(idx, vrs)), flush=True)
""")


def test_libcosimpy_reproduces_fmpy(tmp_path, fmu2):
    pytest.importorskip("libcosimpy")
    h, steps = 0.01, 40
    rng = np.random.default_rng(11)
    J = np.array([[2.0, 0.1, 0.0], [0.1, 3.0, 0.2], [0.0, 0.2, 4.0]])
    q0 = rng.normal(size=(N, 4))
    q0 /= np.linalg.norm(q0, axis=1, keepdims=True)
    xi0, u, p0 = rng.normal(size=(N, 6)), rng.normal(size=(N, 6)), rng.normal(size=(N, 3))
    params = list(zip(layout.vr_inertia(N).tolist(), np.tile(J, (N, 1, 1)).ravel().tolist()))
    params += list(zip(layout.vr_q0(N).tolist(), q0.ravel().tolist()))
    params += list(zip(layout.vr_xi0(N).tolist(), xi0.ravel().tolist()))
    params += list(zip(layout.vr_p0(N).tolist(), p0.ravel().tolist()))
    params += list(zip(layout.vr_input(N).tolist(), u.ravel().tolist()))
    params += [(3, -9.81)]
    vrs = layout.vr_state(N).tolist() + layout.vr_quat(N).tolist()

    with FleetFMU(N, fmu_path=fmu2) as f:
        f.set_real([p[0] for p in params], [p[1] for p in params])
        f.initialize()
        for k in range(steps):
            f.do_step(k * h, h)
        expected = np.concatenate([f.get_state().ravel(), f.get_quat().ravel()])

    script = tmp_path / "cosim_run.py"
    script.write_text(LIBCOSIM_SCRIPT)
    res = subprocess.run([sys.executable, str(script), str(fmu2), str(int(round(h * 1e9))), str(steps),
                          json.dumps(params), json.dumps(vrs)], capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    lines = [ln for ln in res.stdout.splitlines() if ln.startswith("RESULT ")]
    assert len(lines) == 1, res.stdout[-2000:]
    got = np.array(json.loads(lines[0][len("RESULT "):]))
    print("libcosim max |diff|", np.abs(got - expected).max())
    assert np.abs(got - expected).max() <= 1e-12, np.abs(got - expected).max()
    assert np.abs(expected).max() > 0.1


def test_identity_reads_our_fmu_from_its_head_and_anything_else_through_fmpy(tmp_path,
                                                                             monkeypatch):
    """FleetFMU recognises the FMU `build` made for n bodies by the GUID at the head of its
    modelDescription.xml (no full read); an FMU for another n, or one whose GUID is not ours,
    is read by fmpy: a wrong body count is a one-line error, a foreign GUID is the one the file
    declares."""
    import zipfile

    from plant_fmu import fast

    ours = build.fmu_path(N)
    calls = []
    real = fast.read_model_description
    monkeypatch.setattr(fast, "read_model_description",
                        lambda p, *a, **k: calls.append(p) or real(p, *a, **k))
    assert fast._identity(ours, N) == (build.guid(N), build.MODEL_IDENTIFIER)
    assert calls == []
    with pytest.raises(fast.Se3SyncError, match=rf"has {N} bodies, expected {N + 1}$"):
        fast._identity(ours, N + 1)
    assert len(calls) == 1
    other = tmp_path / "other.fmu"
    with zipfile.ZipFile(ours) as src, zipfile.ZipFile(other, "w") as dst:
        for item in src.infolist():
            data = src.read(item)
            if item.filename == "modelDescription.xml":
                data = data.replace(build.guid(N).encode(), b"{00000000-0000-0000-0000-000000000001}")
            dst.writestr(item, data)
    assert fast._identity(other, N) == ("{00000000-0000-0000-0000-000000000001}",
                                        build.MODEL_IDENTIFIER)
    assert len(calls) == 2
    with pytest.raises(FMUError):   # the binary checks the GUID it is instantiated with
        FleetFMU(N, fmu_path=other)
