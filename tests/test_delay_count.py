"""Roots outside the unit circle counted by the argument principle along the agents' tree
(`cosim.analysis.delay_count`), against dense eigenvalues and determinants and the sweep."""
import numpy as np
import pytest
import scipy.sparse as sp

from cosim.analysis import delay_margin as dm
from cosim.analysis.delay_count import TreeDeterminant, roots_outside
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
            f = td.log_dets(z, d).sum()
            assert f.real == pytest.approx(logabs, abs=1e-8)
            assert abs(np.exp(1j * f.imag) - sign) < 1e-8


@pytest.mark.parametrize("d", [0, 24, 25])
def test_roots_outside_equals_dense_eigenvalues(d):
    """hil_6uav (a tree): the count equals the number of eigenvalues of the augmented loop
    (LAPACK, rigid motion's six 1s left out) outside the unit circle, before the margin (24) and
    past it."""
    sc = load_scenario(HIL)
    lin, (P, B, C) = _loop(sc)
    ev = np.linalg.eigvals(dm.augmented(P, B, C, d).toarray())
    ev = ev[np.abs(ev - 1.0) > 1e-7]
    assert ev.size == P.shape[0] + d * C.shape[0] - 6
    k, freqs = roots_outside(TreeDeterminant(lin, P, B, C), P.shape[0], d)
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
