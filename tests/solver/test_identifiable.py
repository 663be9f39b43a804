"""Unknowns the data cannot determine: by correlation and by sigma."""

from __future__ import annotations

import numpy as np

from hartrao_jax.solver._identifiable import unidentifiable


def test_unidentifiable_by_correlation_and_by_sigma():
    names = ["f", "x6", "x7", "x4"]
    C = np.diag([1e-10, 1e-12, 1e-12, 1e-14])
    C[1, 2] = C[2, 1] = 0.995e-12  # x6, x7 confounded
    bad = unidentifiable(C, names, ["x6", "x7", "x4"])
    assert len(bad) == 1 and set(bad[0][0]) == {"x6", "x7"} and bad[0][3] == "correlation"
    C = np.diag([1e-10, (1e-3) ** 2, 1e-14, 1e-14])  # x6 sigma 1e-3 rad >> typical 5e-5
    bad = unidentifiable(C, names, ["x6", "x7", "x4"], typical={"x6": 5e-5, "x7": 5e-5})
    assert [b[0] for b in bad] == [("x6",)] and bad[0][3] == "sigma"
    assert unidentifiable(np.diag([1e-10, 1e-12, 1e-12, 1e-14]), names, ["x6", "x7"]) == []
