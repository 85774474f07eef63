"""FrameDetections: the validated mark follows the very arrays that were checked."""
from __future__ import annotations

from functools import partial

import numpy as np
import pytest

from helpers_scene import random_detections

#: random detections in a 500 px square (``n``, ``j``, ``v`` per call)
_frame = partial(random_detections, xy=(0.0, 500.0), score=0.9, kpts=(0.0, 500.0),
                 verts=(0.0, 500.0))


def test_a_replaced_array_is_checked_again_even_where_its_address_is_reused():
    """The mark is kept against the checked arrays themselves (held, compared by identity),
    not their id(): an array freed and replaced by a new one -- which CPython often allocates
    at the freed address, i.e. with the same id -- is always validated again."""
    fd = _frame()
    shape = fd.verts2d.shape
    for _ in range(50):
        fd.mark_validated()
        fd.verts2d = None  # the checked array is freed (unless the mark holds it) ...
        fd.verts2d = np.full(shape, np.inf, np.float32)  # ... and a new one takes its place
        with pytest.raises(ValueError, match="verts2d: inf in detection 0"):
            fd.validate()
        fd.verts2d = np.zeros(shape, np.float32)
        fd.validate()


def test_the_mark_survives_select_and_goes_with_a_reshaped_array():
    fd = _frame().validate()
    part = fd.select(np.array([0, 2]))
    part.kpts3d[0, 0, 0] = np.nan  # written in place: the writer's responsibility
    assert part.validate() is part
    fd.scores.shape = (3, 1)  # the same array object, another shape: checked again
    with pytest.raises(ValueError, match="score: expected shape"):
        fd.validate()
