"""median0 (tactile/arrays.py) is np.median along the first axis, bit for bit: the calibrator's
common offset and a frame's noise are taken with it, and every output must stay the same."""

from __future__ import annotations

import numpy as np
import pytest
from cellbridge.tactile.arrays import median0
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

# Infinities, huge values and the empty case make np.median itself warn (overflow, mean of an
# empty slice); median0 must answer as it does, warnings and all.
pytestmark = pytest.mark.filterwarnings("ignore::RuntimeWarning")

_VALUES = st.one_of(st.floats(allow_nan=True, allow_infinity=True, width=64),
                    st.sampled_from([0.0, -0.0, 1e-15, -1e-15, 1.5e-13]))


def _same(a: object, b: object) -> bool:
    x, y = np.asarray(a), np.asarray(b)
    return x.shape == y.shape and x.dtype == y.dtype and x.tobytes() == y.tobytes()


@settings(max_examples=400, deadline=None)
@given(hnp.arrays(np.float64, st.tuples(st.integers(1, 40)), elements=_VALUES))
def test_median0_of_a_vector_is_np_median_bit_for_bit(a: np.ndarray) -> None:
    got, want = median0(a.copy()), np.median(a.copy(), axis=0)
    assert _same(got, want) and type(got) is type(want)


@settings(max_examples=400, deadline=None)
@given(hnp.arrays(np.float64, st.tuples(st.integers(1, 40), st.integers(1, 3)), elements=_VALUES))
def test_median0_of_columns_is_np_median_bit_for_bit(a: np.ndarray) -> None:
    assert _same(median0(a.copy()), np.median(a.copy(), axis=0))


def test_median0_leaves_its_input_alone_and_takes_the_empty_case_to_np_median() -> None:
    a = np.array([3.0, 1.0, 2.0])
    assert median0(a) == 2.0 and a.tolist() == [3.0, 1.0, 2.0]
    with np.errstate(invalid="ignore"):
        assert _same(median0(np.zeros((0, 2))), np.median(np.zeros((0, 2)), axis=0))
