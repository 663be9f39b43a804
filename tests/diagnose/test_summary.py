"""The history's mismatch maps: binned when read, as the scans were when taken."""

import gc
import weakref

import numpy as np

from hartrao_jax.diagnose._summary import _dish_map, _snapshot


class _Scan:
    """What the maps read of a scan."""

    def __init__(self, rng, n=5000):
        self.id = "s1"
        self.X_tel = np.column_stack([rng.uniform(-13, 13, n), rng.uniform(-13, 13, n),
                                      np.zeros(n)])
        self.window = np.ones(n, bool)
        self.used = rng.uniform(size=n) > 0.1
        self.mismatch_m = rng.normal(0.0, 1e-3, n)


def test_maps_are_those_of_the_moment_taken():
    sc = _Scan(np.random.default_rng(3))
    before = _dish_map(sc, sc.mismatch_m).astype(np.float32)
    maps = _snapshot([sc])
    # the scan moves on (new arrays, as a refit assigns them) before the map is read
    sc.mismatch_m = sc.mismatch_m + 1.0
    sc.used = ~sc.used
    assert list(maps) == ["s1"] and len(maps) == 1
    np.testing.assert_array_equal(maps["s1"], before)
    assert maps["s1"].dtype == np.float32
    assert not np.allclose(np.nan_to_num(_dish_map(sc, sc.mismatch_m)), np.nan_to_num(before))


def test_maps_do_not_keep_the_scan():
    """A diagnosis kept (its history's maps) does not keep its scans' other arrays."""
    sc = _Scan(np.random.default_rng(4))
    maps = _snapshot([sc])
    alive = weakref.ref(sc)
    del sc
    gc.collect()
    assert alive() is None
    assert maps["s1"].shape == (96, 96)
