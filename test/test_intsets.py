"""core/intsets.py against np.unique on the same inputs."""
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from maem_ros.core.intsets import sorted_unique, unique_inverse

ids = arrays(np.int64, st.integers(0, 300), elements=st.integers(0, 49))


@settings(max_examples=200, deadline=None)
@given(ids)
def test_sorted_unique_equals_numpy(x):
    got = sorted_unique(x)
    assert got.dtype == x.dtype
    np.testing.assert_array_equal(got, np.unique(x))


@settings(max_examples=200, deadline=None)
@given(ids, st.integers(0, 20))
def test_unique_inverse_equals_numpy(x, slack):
    values, inverse = unique_inverse(x, 50 + slack)
    want_values, want_inverse = np.unique(x, return_inverse=True)
    np.testing.assert_array_equal(values, want_values)
    np.testing.assert_array_equal(inverse, want_inverse)
    np.testing.assert_array_equal(values[inverse], x)


def test_negative_codes_sort_too():
    np.testing.assert_array_equal(sorted_unique(np.array([3, -2, 3, -2, 0])), [-2, 0, 3])


def test_empty():
    assert sorted_unique(np.zeros(0, np.int64)).size == 0
    values, inverse = unique_inverse(np.zeros(0, np.int64), 4)
    assert values.size == 0 and inverse.size == 0
