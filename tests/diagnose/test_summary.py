"""The history's mismatch maps: binned when read, as the scans were when taken."""

from types import SimpleNamespace

import numpy as np

from hartrao_jax.diagnose._summary import _dish_map, _snapshot


def _scan(rng, n=5000):
    X = np.column_stack([rng.uniform(-13, 13, n), rng.uniform(-13, 13, n), np.zeros(n)])
    d = rng.normal(0.0, 1e-3, n)
    return SimpleNamespace(id="s1", X_tel=X, window=np.ones(n, bool),
                           used=rng.uniform(size=n) > 0.1, mismatch_m=d)


def test_maps_are_those_of_the_moment_taken():
    sc = _scan(np.random.default_rng(3))
    before = _dish_map(sc, sc.mismatch_m).astype(np.float32)
    maps = _snapshot([sc])
    # the scan moves on (new arrays, as a refit assigns them) before the map is read
    sc.mismatch_m = sc.mismatch_m + 1.0
    sc.used = ~sc.used
    assert list(maps) == ["s1"] and len(maps) == 1
    np.testing.assert_array_equal(maps["s1"], before)
    assert maps["s1"].dtype == np.float32
    assert not np.allclose(np.nan_to_num(_dish_map(sc, sc.mismatch_m)), np.nan_to_num(before))
