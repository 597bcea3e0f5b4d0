"""Hardening of the plant FMU (issue 13): bounded work per doStep, validated FMU states, double free,
inertia and mass scales, one-line errors.  Both FMI 2.0 and FMI 3.0 layers are exercised.

Anything that used to hang or abort runs in a child process (this file run as a script) with a
timeout, so that a regression fails the test instead of hanging or killing the suite.
"""
from __future__ import annotations

import json
import math
import random
import struct
import subprocess
import sys

import numpy as np
import pytest

from plant_fmu import build, layout
from plant_fmu.fast import FleetFMU, FMUError

HEADER = 40          # bytes of the serialized-state header (see docs/reference/plant-fmu.md)
CHECKSUM = slice(32, 40)
LIMIT = 1_000_000    # body-substeps per doStep (docs/reference/plant-fmu.md "Limits")
TIMEOUT = 120        # s for a child process: generous under load; a regression takes ~1 hour


# ------------------------------------------------------------------ independent helpers


def fnv1a64(data: bytes) -> int:
    """FNV-1a, 64 bit, written from its definition (offset basis and prime of the FNV spec)."""
    h = 0xcbf29ce484222325
    for b in data:
        h = ((h ^ b) * 0x100000001b3) & 0xFFFFFFFFFFFFFFFF
    return h


def reseal(blob: bytes) -> bytes:
    """The blob with a correct checksum (FNV-1a of everything, checksum field zeroed)."""
    b = bytearray(blob)
    b[CHECKSUM] = bytes(8)
    b[CHECKSUM] = struct.pack("=Q", fnv1a64(bytes(b)))
    return bytes(b)


def find_once(blob: bytes, values) -> int:
    """Offset of the packed doubles `values` in blob; they must occur exactly once."""
    pat = struct.pack(f"={len(values)}d", *values)
    assert blob.count(pat) == 1, values
    return blob.find(pat)


def patch(blob: bytes, offset: int, values) -> bytes:
    b = bytearray(blob)
    b[offset:offset + 8 * len(values)] = struct.pack(f"={len(values)}d", *values)
    return bytes(b)


def test_fnv1a64_matches_the_published_test_vectors():
    assert fnv1a64(b"") == 0xcbf29ce484222325
    assert fnv1a64(b"a") == 0xaf63dc4c8601ec8c
    assert fnv1a64(b"foobar") == 0x85944171f73967e8


# ------------------------------------------------------------------ child process side


class Slave:
    """fmpy's FMU2Slave / FMU3Slave behind one interface; statuses instead of exceptions."""

    def __init__(self, version: int, n: int):
        from fmpy import extract, read_model_description

        self.v, self.n = version, n
        path = build.fmu_path(n, fmi_version=version)
        md = read_model_description(str(path))
        kw = dict(guid=md.guid, unzipDirectory=extract(str(path)), modelIdentifier=md.coSimulation.modelIdentifier,
                  instanceName="hard")
        self.messages: list[str] = []
        if version == 2:
            from fmpy.fmi2 import FMU2Slave, fmi2CallbackFunctions, fmi2CallbackLoggerTYPE

            self.cb = fmi2CallbackFunctions()
            self.cb.logger = fmi2CallbackLoggerTYPE(lambda env, name, st, cat, msg: self.messages.append(msg.decode()))
            self.s = FMU2Slave(**kw)
            self.s.instantiate(callbacks=self.cb)
        else:
            from fmpy.fmi3 import FMU3Slave

            self.s = FMU3Slave(**kw)
            self.s.instantiate(logMessage=lambda env, st, cat, msg: self.messages.append(msg.decode()))

    def call(self, f, *args):
        """(status, result) of an fmpy call; fmpy raises FMICallException for status > warning"""
        try:
            return 0, f(*args)
        except Exception as exc:
            return getattr(exc, "status", -1), None

    def set(self, values: dict):
        f = self.s.setReal if self.v == 2 else self.s.setFloat64
        f(list(values), [float(x) for x in values.values()])

    def get(self, vrs):
        f = self.s.getReal if self.v == 2 else self.s.getFloat64
        return f([int(v) for v in vrs])

    def init(self, values: dict):
        if self.v == 2:
            self.s.setupExperiment(startTime=0.0)
            self.s.enterInitializationMode()
        else:
            self.s.enterInitializationMode(startTime=0.0)
        self.set(values)
        return self.call(self.s.exitInitializationMode)[0]

    def step(self, t, h):
        return self.call(self.s.doStep, t, h)[0]

    def get_state(self):
        return self.s.getFMUstate() if self.v == 2 else self.s.getFMUState()

    def set_state(self, st):
        return self.call(self.s.setFMUstate if self.v == 2 else self.s.setFMUState, st)[0]

    def serialize(self, st) -> bytes:
        return bytes(self.s.serializeFMUstate(st) if self.v == 2 else self.s.serializeFMUState(st))

    def deserialize(self, blob: bytes, into=None):
        f = self.s.deSerializeFMUstate if self.v == 2 else self.s.deserializeFMUState
        return self.call(f, blob, into)

    def free_raw(self):
        """fmiNFreeInstance through the raw binding (fmpy's freeInstance also unloads the library)"""
        (self.s.fmi2FreeInstance if self.v == 2 else self.s.fmi3FreeInstance)(self.s.component)


def _tumbling(n: int) -> dict:
    """distinctive parameters: nonzero spin and velocity, gravity, h_internal = 2.5e-4"""
    vals = {layout.VR_H_INTERNAL: 2.5e-4, 3: -9.81}
    for b in range(n):
        base = layout.body_base(b)
        vals[base + 40] = 1.25 + 0.5 * b
        vals.update({base + 57 + k: x * (1 + 0.1 * b) for k, x in enumerate((0.4, 1.3, -0.2, 0.3, -0.1, 0.7))})
    return vals


def child_hang(version: int, case: str) -> dict:
    n = 6
    p = Slave(version, n)
    out = {}
    if case == "big_step":
        out["init"] = p.init({})
        out["step"] = p.step(0.0, 1e6)
        out["after"] = p.step(0.0, 0.01)  # refused before any work: the instance stays usable
    elif case == "tiny_h_internal":
        out["init"] = p.init({layout.VR_H_INTERNAL: 1e-12})
        out["step"] = p.step(0.0, 1.0)    # still in initialization mode: an illegal call
    elif case == "patched_state":
        out["init"] = p.init(_tumbling(n))
        p.step(0.0, 0.01)
        st = p.get_state()
        blob = p.serialize(st)
        out["checksum_ok"] = reseal(blob) == blob
        off = find_once(blob, [2.5e-4])
        out["deserialize"], st2 = p.deserialize(reseal(patch(blob, off, [1e-12])))
        out["deserialize_unsealed"] = p.deserialize(patch(blob, off, [1e-12]))[0]
        out["step"] = p.step(0.01, 1.0)   # the instance keeps its own, valid state
    out["messages"] = p.messages
    return out


def child_fuzz(version: int, seed: int) -> dict:
    """200 corrupted serialized states: none may be accepted, none may hang or crash."""
    n = 2
    p = Slave(version, n)
    assert p.init(_tumbling(n)) == 0
    for k in range(5):
        p.step(0.01 * k, 0.01)
    vr_state = layout.vr_state(n)
    x = p.get(vr_state)  # [p, R, xi] per body
    st = p.get_state()
    blob = p.serialize(st)
    rng = random.Random(seed)
    R1 = x[3:12]
    off_R1 = find_once(blob, R1)
    off_xi1 = find_once(blob, x[12:18])
    off_p2 = find_once(blob, x[18:21])
    off_h = find_once(blob, [2.5e-4])
    off_m1 = find_once(blob, [1.25])
    off_t = find_once(blob, [0.05])
    swapped = R1[3:6] + R1[0:3] + R1[6:9]  # rows 1, 2 swapped: orthogonal, det = -1
    corrupt = [
        lambda b: patch(b, off_xi1 + 8 * rng.randrange(6), [math.nan]),
        lambda b: patch(b, off_p2 + 8 * rng.randrange(3), [rng.choice([math.inf, -math.inf])]),
        lambda b: patch(b, off_R1, [r * (1 + rng.choice([-1, 1]) * 10 ** rng.uniform(-5, -1)) for r in R1]),
        lambda b: patch(b, off_R1, swapped),
        lambda b: patch(b, off_h, [rng.choice([1e-12, 1e-300, 0.0, -2.5e-4, math.nan])]),
        lambda b: patch(b, off_m1, [rng.choice([-1.25, 0.0, 1e-300, 1e300, math.nan])]),
        lambda b: patch(b, off_m1 + 8, [rng.uniform(5, 10)]),  # J[1,1] of body 1 (follows m)
        lambda b: patch(b, off_t, [rng.choice([math.inf, math.nan])]),
        lambda b: b[:HEADER] + struct.pack("=i", rng.choice([0, 3, 6, 32 + 1, -1])) + b[HEADER + 4:],  # mode
    ]
    results = []
    for i in range(200):
        kind = i % 4
        if kind == 0:    # random bytes of the right length
            bad = bytes(rng.getrandbits(8) for _ in range(len(blob)))
        elif kind == 1:  # valid header, random payload, correct checksum
            bad = reseal(blob[:HEADER] + bytes(rng.getrandbits(8) for _ in range(len(blob) - HEADER)))
        elif kind == 2:  # one field corrupted, correct checksum
            bad = reseal(corrupt[(i // 4) % len(corrupt)](blob))
        else:            # one flipped bit anywhere (checksum byte included), checksum not recomputed
            b = bytearray(blob)
            j = rng.randrange(len(b)) if i % 8 == 3 else rng.randrange(CHECKSUM.start, CHECKSUM.stop)
            b[j] ^= 1 << rng.randrange(8)
            bad = bytes(b)
        assert bad != blob
        status, _ = p.deserialize(bad)
        results.append(status)
    # a refused blob leaves an existing FMU state untouched; the genuine one still round-trips
    status, st_ok = p.deserialize(blob)
    status_into, _ = p.deserialize(reseal(patch(blob, off_h, [1e-12])), st_ok)
    p.step(0.05, 0.01)
    set_status = p.set_state(st_ok)
    restored = p.get(vr_state)
    return dict(results=results, checksum_ok=reseal(blob) == blob, genuine=status, into=status_into,
                set=set_status, same=restored == x, n_messages=len(p.messages),
                longest=max(len(m) for m in p.messages))


def child_double_free(version: int, n: int) -> dict:
    p = Slave(version, n)
    p.init({})
    p.free_raw()
    p.free_raw()
    if version == 2:
        after = p.call(p.s.fmi2DoStep, p.s.component, 0.0, 0.01, 1)[0]
    else:
        after = p.call(p.s.fmi3Terminate, p.s.component)[0]
    return dict(after=after, messages=p.messages)


def run_child(*args) -> dict:
    """runs this file as a script in a new process; a hang is a TimeoutExpired, an abort a bad rc"""
    proc = subprocess.run([sys.executable, __file__, *map(str, args)], capture_output=True, text=True,
                          timeout=TIMEOUT)
    assert proc.returncode == 0, (proc.returncode, proc.stderr[-2000:])
    return json.loads(proc.stdout.strip().splitlines()[-1])


# ------------------------------------------------------------------ 11: bounded work per doStep

ERR = 3  # fmi2Error == fmi3Error


@pytest.mark.parametrize("version", [2, 3])
def test_huge_communication_step_is_refused_at_once(version):
    r = run_child("hang", version, "big_step")
    assert r["init"] == 0 and r["step"] == ERR and r["after"] == 0
    text = " | ".join(r["messages"])
    assert f"limit of {LIMIT} body-steps per call ({LIMIT // 6} per body)" in text, text


@pytest.mark.parametrize("version", [2, 3])
def test_tiny_internal_step_is_refused(version):
    r = run_child("hang", version, "tiny_h_internal")
    assert r["init"] == ERR and r["step"] == ERR
    assert any("h_internal = 1e-12 must be finite and >= 1e-09" in m for m in r["messages"]), r["messages"]


@pytest.mark.parametrize("version", [2, 3])
def test_deserialized_state_with_a_tiny_internal_step_is_refused(version):
    r = run_child("hang", version, "patched_state")
    assert r["init"] == 0 and r["checksum_ok"]
    assert r["deserialize"] == ERR and r["deserialize_unsealed"] == ERR and r["step"] == 0
    text = " | ".join(r["messages"])
    assert "h_internal = 1e-12" in text and "checksum mismatch" in text, text


def test_work_budget_boundary_is_exact():
    """N x ceil(h / h_internal) <= LIMIT is accepted, one substep more is refused (nothing done)."""
    hi = 2.0 ** -10  # h / hi exact in binary
    with FleetFMU(1, fmu_path=build.fmu_path(1)) as f:
        f.set_parameters(h_internal=hi, xi0=[[0.1, 0.2, 0.3, 1.0, 0.0, 0.0]])
        f.initialize()
        f.do_step(0.0, LIMIT * hi)
        x = f.get_state().copy()
        assert np.all(np.isfinite(x))
        t = LIMIT * hi
        with pytest.raises(FMUError, match=f"limit of {LIMIT} body-steps per call") as e:
            f.do_step(t, (LIMIT + 1) * hi)
        assert "\n" not in str(e.value)
        assert f.get_state().tobytes() == x.tobytes()
        f.do_step(t, 0.01)  # still usable


def test_normal_use_stays_accepted():
    from fmpy import simulate_fmu

    with FleetFMU(6, fmu_path=build.fmu_path(6)) as f:
        f.set_parameters(h_internal=1e-4)
        f.initialize()
        for k, h in enumerate((1e-4, 4e-3, 1.0)):
            f.do_step(float(k), h)
        assert np.all(np.isfinite(f.get_state()))
    res = simulate_fmu(str(build.fmu_path(6)), stop_time=3.0, output_interval=1.0)
    assert res["time"][-1] == pytest.approx(3.0) and np.all(np.isfinite(res[res.dtype.names[1]]))


# ------------------------------------------------------------------ 12: validated FMU states


@pytest.mark.parametrize("version", [2, 3])
def test_random_and_corrupted_states_are_all_refused(version):
    r = run_child("fuzz", version, 1234 + version)
    assert r["checksum_ok"]
    assert len(r["results"]) == 200 and set(r["results"]) == {ERR}, r["results"]
    assert r["genuine"] == 0 and r["into"] == ERR and r["set"] == 0 and r["same"]
    assert r["longest"] < 300  # every logged message is one short line


def test_legitimate_states_of_every_mode_still_round_trip():
    """not over-strict: a state after a failed step (non-finite by nature) and a state before
    initialization with a parameter that initialization will refuse both deserialize; the
    parameter is then refused where it always was, at exitInitializationMode."""
    with FleetFMU(1, fmu_path=build.fmu_path(1)) as f:
        f.set_parameters(J=np.eye(3) * 1e-200)
        f.initialize()
        f.set_input(np.array([[1e200, 0.0, 0.0, 0.0, 0.0, 0.0]]))  # J^-1 tau = 1e400: overflows
        with pytest.raises(FMUError, match="no longer finite"):
            f.do_step(0.0, 0.01)
        s = f.get_fmu_state()
        blob = f.serialize_fmu_state(s)
        s2 = f.deserialize_fmu_state(blob)
        assert f.serialize_fmu_state(s2) == blob
        f.free_fmu_state(s)
        f.free_fmu_state(s2)
    with FleetFMU(1, fmu_path=build.fmu_path(1)) as f, FleetFMU(1, fmu_path=build.fmu_path(1)) as g:
        f.set_parameters(mass=-1.0)
        s = f.get_fmu_state()
        s2 = g.deserialize_fmu_state(f.serialize_fmu_state(s))
        g.set_fmu_state(s2)
        with pytest.raises(FMUError, match=r"body\[1\]\.m = -1 must be > 0"):
            g.initialize()
        f.free_fmu_state(s)
        g.free_fmu_state(s2)


# ------------------------------------------------------------------ 13: double free


@pytest.mark.parametrize("version,n", [(2, 1), (2, 6), (3, 1), (3, 6)])
def test_double_free_is_a_logged_error_not_an_abort(version, n):
    r = run_child("free", version, n)
    fn = f"fmi{version}FreeInstance"
    assert any(m == f"{fn}: called with an instance that was already freed (ignored)" for m in r["messages"]), r
    assert r["after"] == ERR
    assert any("already freed" in m and m.startswith(f"fmi{version}") and fn not in m for m in r["messages"]), r


# ------------------------------------------------------------------ 24: inertia and mass scales


def _refusal(J=None, mass=None, n=1, body=0) -> FMUError:
    with FleetFMU(n, fmu_path=build.fmu_path(n)) as f:
        kw = {}
        if J is not None:
            Js = np.tile(np.eye(3), (n, 1, 1))
            Js[body] = J
            kw["J"] = Js
        if mass is not None:
            ms = np.ones(n)
            ms[body] = mass
            kw["mass"] = ms
        f.set_parameters(**kw)
        with pytest.raises(FMUError) as e:
            f.initialize()
        return e.value


@pytest.mark.parametrize("J,why", [
    (np.diag([1.0, 1.0, 5.0]) * 1e-170, "violates the triangle inequality"),  # underflowed to "valid" before
    (np.diag([1.0, 1.0, 5.0]) * 1e170, "violates the triangle inequality"),
    (np.diag([1e-300] * 3), "outside the accepted range"),
    (np.diag([1e300] * 3), "outside the accepted range"),
    (np.diag([1.0, 2.0, -2.0]) * 1e-200, "not positive definite"),
    (np.array([[1.0, 0.5, 0], [0, 1.0, 0], [0, 0, 1.0]]) * 1e-200, "not symmetric"),
])
def test_bad_inertia_is_refused_at_any_scale_naming_body_and_J(J, why):
    e = _refusal(J=J, n=3, body=2)
    first = e.messages[0]
    assert first.startswith("body[3].J") and why in first and len(first) < 200, e.messages
    assert "\n" not in str(e)


@pytest.mark.parametrize("mass", [1e-300, 1e300, 0.0, -1.0])
def test_bad_mass_is_refused_naming_the_body(mass):
    e = _refusal(mass=mass, n=2, body=1)
    assert e.messages[0].startswith(f"body[2].m = {mass:g}"), e.messages


def _trajectory(scale: float) -> bytes:
    """Euler and Newton are invariant under (J, m, u) -> s (J, m, u); with s a power of two the
    integrator's arithmetic is exactly scaled too, so the trajectory must agree bit for bit."""
    Q = np.array([[0.36, 0.48, -0.8], [-0.8, 0.6, 0.0], [0.48, 0.64, 0.6]])
    J = Q @ np.diag([1.0, 2.0, 2.0]) @ Q.T
    u = np.array([[0.3, -0.2, 0.1, 1.0, 0.5, -0.25]])
    with FleetFMU(1, fmu_path=build.fmu_path(1)) as f:
        f.set_parameters(mass=1.5 * scale, J=J * scale, xi0=[[0.4, 1.3, -0.2, 0.3, -0.1, 0.7]],
                         gravity=[0.0, 0.0, -9.81], h_internal=1e-3)
        f.initialize()
        f.set_input(u * scale)
        for k in range(20):
            f.do_step(0.01 * k, 0.01)
        x = f.get_state().copy()
    assert np.all(np.isfinite(x)) and np.abs(x[0, 12:15]).max() > 0.1
    return x.tobytes()


def test_scaled_bodies_within_the_range_move_identically():
    ref = _trajectory(1.0)
    assert _trajectory(2.0 ** 664) == ref   # J ~ 1e200 (refused before as "not positive definite")
    assert _trajectory(2.0 ** -664) == ref  # J ~ 1e-200 (J^-1 overflowed before)


def test_diag_122_times_1e200_is_accepted_and_steps_finitely():
    with FleetFMU(1, fmu_path=build.fmu_path(1)) as f:
        f.set_parameters(J=np.diag([1.0, 2.0, 2.0]) * 1e200, mass=1e200, xi0=[[0.1, 1.0, 0.2, 0, 0, 1]])
        f.initialize()
        f.set_input(np.array([[1.0, 2.0, 3.0, 1.0, 1.0, 1.0]]) * 1e200)
        f.do_step(0.0, 0.1)
        x = f.get_state()
        assert np.all(np.isfinite(x))
        R = x[0, 3:12].reshape(3, 3)
        assert np.abs(R.T @ R - np.eye(3)).max() < 1e-12


# ------------------------------------------------------------------ 10: one-line errors


def test_fmu_error_is_one_short_line_with_all_messages_kept():
    n = 6
    with FleetFMU(n, fmu_path=build.fmu_path(n)) as f:
        f.set_parameters(J=np.tile(np.diag([1.0, 1.0, 5.0]), (n, 1, 1)))
        with pytest.raises(FMUError) as e:
            f.initialize()
    text = str(e.value)
    assert "\n" not in text and len(text) < 500, text
    assert text.startswith("fmi2ExitInitializationMode returned fmi2Error: body[1].J: violates the triangle")
    per_body = [m for m in e.value.messages if "triangle inequality" in m]
    assert [m[:8] for m in per_body] == [f"body[{i}]." for i in range(1, n + 1)]
    assert all(len(m) < 200 for m in e.value.messages)
    shown = text.count("triangle inequality")
    assert text.endswith(f"(+{len(e.value.messages) - shown} more)") and shown < n


if __name__ == "__main__":
    kind, *rest = sys.argv[1:]
    if kind == "hang":
        res = child_hang(int(rest[0]), rest[1])
    elif kind == "fuzz":
        res = child_fuzz(int(rest[0]), int(rest[1]))
    else:
        res = child_double_free(int(rest[0]), int(rest[1]))
    print(json.dumps(res))
