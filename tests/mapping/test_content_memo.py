"""core.memo.content_memo: the anchor passes' repeated slice fits come from the memo, keyed by the
content of the arguments (issue 16)."""

import numpy as np

from forestmap_assets.core.memo import content_key, content_memo


def test_the_same_content_hits_and_any_change_misses():
    calls = []

    @content_memo(3)
    def f(a, centre, **kw):
        calls.append(1)
        return (float(a.sum()), centre, tuple(sorted(kw)))

    a = np.arange(6.0).reshape(3, 2)
    first = f(a, (1.0, 2.0), sides=None, k=0.5)
    assert f(a.copy(), (1.0, 2.0), sides=None, k=0.5) is first and len(calls) == 1  # equal content
    b = a.copy()
    b[2, 1] = np.nextafter(b[2, 1], 10)  # one ulp
    f(b, (1.0, 2.0), sides=None, k=0.5)
    f(a.astype(np.float32), (1.0, 2.0), sides=None, k=0.5)  # another dtype
    f(a.reshape(2, 3), (1.0, 2.0), sides=None, k=0.5)  # another shape
    assert len(calls) == 4
    f(a, (1.0, 2.0), sides=(a[:, 0], a[:, 1]), k=0.5)  # arrays inside a tuple keyword
    assert len(calls) == 5
    f(a, (1.0, 2.0), sides=None, k=0.5)  # evicted (three kept)
    assert len(calls) == 6


def test_keys_tell_types_and_nan_apart():
    assert content_key((1,), {}) != content_key((1.0,), {})
    assert content_key((np.float64(1.0),), {}) != content_key((1.0,), {})
    assert content_key((float("nan"),), {}) == content_key((float("nan"),), {})
    assert content_key(((1, 2),), {}) != content_key(([1, 2],), {})
    assert content_key((), {"a": 1, "b": 2}) == content_key((), {"b": 2, "a": 1})
    assert content_key((np.zeros((2, 3)),), {}) != content_key((np.zeros((3, 2)),), {})


def test_slice_fits_are_the_functions_own():
    from forestmap_assets.core.mapping.stem_slices import slice_dbh

    rng = np.random.default_rng(4)
    ang = rng.uniform(-np.pi, np.pi, 400)  # seen all round (no sensor: no incidence test)
    xy = np.column_stack([0.2 * np.cos(ang), 0.2 * np.sin(ang)]) + rng.normal(0, 0.003, (400, 2))
    slice_dbh.cache_clear()
    a = slice_dbh(xy, None, (0.01, 0.0), 0.19)
    b = slice_dbh(xy.copy(), None, (0.01, 0.0), 0.19)
    assert a is b and 0.39 < a.dbh_m < 0.41, a
    assert slice_dbh(xy, None, (0.01, 0.0), 0.18) is not a  # another start radius
    slice_dbh.cache_clear()
    assert slice_dbh(xy, None, (0.01, 0.0), 0.19) == a
