"""Roots outside the unit circle counted by the argument principle along the agents' tree
(`cosim.analysis.delay_count`), against dense eigenvalues and determinants and the sweep."""
import numpy as np
import pytest
import scipy.sparse as sp

from cosim.analysis import delay_margin as dm
from cosim.analysis import delay_count as dc
from cosim.analysis.delay_count import (InputDeterminant, TreeDeterminant, determinant_on_tree,
                                        roots_outside)
from cosim.analysis.stability_cases import tree_scenario_text
from cosim.analysis.stability_sparse import Linearisation
from cosim.scenario import load_scenario, parse_scenario

HIL = "scenarios/hil_6uav.toml"


def _loop(sc):
    lin = Linearisation(sc, True, force_sparse=True)
    return lin, dm.delayed_parts(lin, sc.step)


def test_tree_determinant_is_the_determinant_of_M():
    """The pivot blocks' log-determinants sum to log det M(z), M(z) = zI − Φ₀ − z^{−d}BC, taken
    dense (modulus, and phase mod 2π), on a 12-agent tree, on and off the unit circle."""
    sc = parse_scenario(tree_scenario_text(12, "random", 0), "t", "t.toml")
    lin, (P, B, C) = _loop(sc)
    td = TreeDeterminant(lin, P, B, C, root=3)
    n = P.shape[0]
    for z in (np.exp(0.03j), np.exp(2.0j), 1.01 * np.exp(0.3j), 0.9 + 0.2j):
        for d in (0, 7, 23):
            M = (z * sp.identity(n) - P - z ** (-d) * (B @ C)).toarray()
            sign, logabs = np.linalg.slogdet(M)
            f = td.log_dets([z], d)[0].sum()
            assert f.real == pytest.approx(logabs, abs=1e-8)
            assert abs(np.exp(1j * f.imag) - sign) < 1e-8


def test_input_determinant_times_the_plants_is_the_determinant_of_M():
    """det(zI − Φ₀) (dense) times the pivot blocks of I − z^{−d}T(z) eliminated in the delayed
    inputs' coordinates is det M(z), modulus and phase, on and off the circle; the blocks are as
    many as the agents and each is as large as the agent's inputs (6 + owned edges)."""
    sc = parse_scenario(tree_scenario_text(12, "random", 0), "t", "t.toml")
    lin, (P, B, C) = _loop(sc)
    idt = InputDeterminant(lin, P, B, C, root=5)
    n = P.shape[0]
    assert idt.r.sum() == C.shape[0] and idt.r.size == 12
    zs = [np.exp(0.03j), np.exp(2.0j), 1.01 * np.exp(0.3j), 0.9 + 0.2j]
    for d in (0, 7, 23):
        f = idt.log_dets(zs, d).sum(axis=1)
        for z, fz in zip(zs, f):
            M = (z * sp.identity(n) - P - z ** (-d) * (B @ C)).toarray()
            sign, logabs = np.linalg.slogdet(M)
            s0, l0 = np.linalg.slogdet(z * np.eye(n) - P.toarray())
            assert fz.real + l0 == pytest.approx(logabs, abs=1e-8)
            assert abs(np.exp(1j * fz.imag) * s0 - sign) < 1e-8


def test_fixed_half_turns_count_the_plants_roots_inside_and_the_fallback():
    """The phase of det(zI − Φ₀) is not sampled: `fixed_half_turns` must equal the number of
    eigenvalues of the dense Φ₀ inside the circle. Where Φ₀ has one on the circle T has a pole
    there, the input elimination refuses, and `determinant_on_tree` counts on the whole state."""
    sc = load_scenario(HIL)
    lin, (P, B, C) = _loop(sc)
    ev = np.linalg.eigvals(P.toarray())
    assert InputDeterminant(lin, P, B, C).fixed_half_turns == int((np.abs(ev) < 1.0).sum())
    assert isinstance(determinant_on_tree(lin, P, B, C), InputDeterminant)
    eye = sp.identity(P.shape[0], format="csr")
    with pytest.raises(ValueError, match="unit circle"):
        InputDeterminant(lin, eye, B, C)
    assert isinstance(determinant_on_tree(lin, eye, B, C), TreeDeterminant)


def test_frequencies_shared_among_threads_give_the_same_phases(monkeypatch):
    """One worker or two: the same log-determinants, bit for bit (each z is one kernel call's
    own work)."""
    sc = parse_scenario(tree_scenario_text(12, "random", 1), "t", "t.toml")
    lin, (P, B, C) = _loop(sc)
    idt = InputDeterminant(lin, P, B, C)
    zs = np.exp(1j * np.linspace(0.01, 3.0, 9))
    monkeypatch.setattr(dc, "_WORKERS", 1)
    one = idt.log_dets(zs, 11)
    monkeypatch.setattr(dc, "_WORKERS", 2)
    assert np.array_equal(idt.log_dets(zs, 11), one)


@pytest.mark.parametrize("d", [0, 24, 25])
@pytest.mark.parametrize("kind", [InputDeterminant, TreeDeterminant])
def test_roots_outside_equals_dense_eigenvalues(d, kind):
    """hil_6uav (a tree): the count equals the number of eigenvalues of the augmented loop
    (LAPACK, rigid motion's six 1s left out) outside the unit circle, before the margin (24) and
    past it."""
    sc = load_scenario(HIL)
    lin, (P, B, C) = _loop(sc)
    ev = np.linalg.eigvals(dm.augmented(P, B, C, d).toarray())
    ev = ev[np.abs(ev - 1.0) > 1e-7]
    assert ev.size == P.shape[0] + d * C.shape[0] - 6
    k, freqs = roots_outside(kind(lin, P, B, C), P.shape[0], d)
    assert k == int((np.abs(ev) > 1.0).sum())
    assert freqs > 40


def test_margin_by_count_equals_the_sweep_and_radii():
    """On hil_6uav and a 12-agent tree the margin from counts equals the one from the sweep and
    the spectral radii; the report gives the counts at the margin and one past it."""
    for sc in (load_scenario(HIL), parse_scenario(tree_scenario_text(12, "random", 0), "t",
                                                  "t.toml")):
        lin = Linearisation(sc, True, force_sparse=True)
        seen = []
        a = dm.delay_margin(sc, lin=lin, count=True,
                            progress=lambda d, r, s, outside=None: seen.append((d, outside)))
        b = dm.delay_margin(sc, lin=lin, count=False)
        d = a["delay_margin_steps"]
        assert d == b["delay_margin_steps"] and d > 0
        assert a["outside_at_margin"] == 0 and a["outside_beyond"] > 0
        assert dict(seen)[d] == 0 and dict(seen)[d + 1] == a["outside_beyond"]
        assert "argument principle" in a["delay_method"]


@pytest.mark.parametrize("start", [1, 40])
def test_margin_by_count_from_below_and_from_above(monkeypatch, start):
    """The search gives hil_6uav's margin (24, as the sweep and radii) whether it starts far
    below (grows by a quarter) or above it (halves, then bisects); d_cap below the margin ends
    with 'stable for every delay up to d_cap'."""
    sc = load_scenario(HIL)
    lin = Linearisation(sc, True, force_sparse=True)
    monkeypatch.setattr(dm, "COUNT_START", start)
    seen = []
    a = dm.delay_margin(sc, lin=lin, count=True,
                        progress=lambda d, r, s, outside=None: seen.append((d, outside)))
    assert a["delay_margin_steps"] == 24 and a["outside_at_margin"] == 0
    ks = dict(seen)
    assert all((k == 0) == (d <= 24) for d, k in ks.items())
    assert (min(ks) if start < 24 else max(ks)) == start
    capped = dm.delay_margin(sc, lin=lin, count=True, d_cap=10)
    assert capped["delay_margin_steps"] is None
    assert capped["delay_method"].startswith("stable for every delay up to 10 steps")


@pytest.mark.parametrize("hybrid,masses", [(False, False), (True, True)])
def test_count_equals_the_sweep_without_theta_and_with_unequal_vehicles(hybrid, masses):
    """Without θ (every agent's inputs are its wrench alone) and with a different mass on every
    vehicle (every agent its own kind, no T shared): the counted margin equals the sweep's and
    radii's on a 20-agent tree."""
    m = np.random.default_rng(5).uniform(1.5, 4.0, 20) if masses else None
    sc = parse_scenario(tree_scenario_text(20, "random", 2, m), "t", "t.toml")
    lin = Linearisation(sc, hybrid, force_sparse=True)
    a = dm.delay_margin(sc, law=hybrid, lin=lin, count=True)
    b = dm.delay_margin(sc, law=hybrid, lin=lin, count=False)
    assert a["delay_margin_steps"] == b["delay_margin_steps"] > 0
    assert b["rho_at_margin"] < 1.0 <= b["rho_beyond"] and a["outside_beyond"] > 0
    if masses:
        P, B, C = dm.delayed_parts(lin, sc.step)
        assert len(InputDeterminant(lin, P, B, C).tb) == 20
