"""The one-point paths of the EI maximisation (fast campaigns) give the batch paths' bits."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hilbo_core.acquisition import _check_predict, _log_h
from hilbo_core.errors import EstimatorError


@settings(max_examples=200, deadline=None)
@given(st.floats(-80.0, 40.0, allow_nan=False))
def test_one_element_log_h_equals_the_masked_batch(z: float) -> None:
    # In a batch with values of every branch the one-element fast path is not taken.
    batch = np.array([z, -60.0, -10.0, 3.0])
    one = _log_h(np.array([z]))
    assert one.shape == (1,)
    assert np.array_equal(one, _log_h(batch)[:1])
    assert np.array_equal(_log_h(np.float64(z)).reshape(1), one)


@pytest.mark.parametrize(("mean", "var"), [(np.nan, 1.0), (0.0, -1e-3), (0.0, np.inf), (np.inf, 1.0)])
def test_one_point_check_rejects_what_the_batch_check_rejects(mean: float, var: float) -> None:
    for m in (1, 2):
        with pytest.raises(EstimatorError, match="non-finite mean or a negative/non-finite variance"):
            _check_predict(np.full(m, mean), np.full(m, var), m)
