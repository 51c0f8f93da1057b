"""gil.quick_handoff(): a short GIL switch interval while HybridGI renders, restored after."""

from __future__ import annotations

import sys

import pytest

from hybridgi_core import gil
from tests.threads import held_on_another_thread


def test_the_interval_is_short_while_any_holder_is_inside_and_restored_after_the_last():
    before = sys.getswitchinterval()
    assert before != gil.SWITCH_INTERVAL_S
    with held_on_another_thread(gil.quick_handoff):
        assert sys.getswitchinterval() == pytest.approx(gil.SWITCH_INTERVAL_S)
        with gil.quick_handoff():
            assert gil.holders() == 2
        assert sys.getswitchinterval() == pytest.approx(gil.SWITCH_INTERVAL_S)  # the other thread holds it
    assert gil.holders() == 0 and sys.getswitchinterval() == pytest.approx(before)


def test_a_failing_block_restores_the_interval():
    before = sys.getswitchinterval()
    with pytest.raises(ValueError), gil.quick_handoff():
        raise ValueError("a frame failed")
    assert gil.holders() == 0 and sys.getswitchinterval() == pytest.approx(before)


def test_the_render_scope_holds_the_short_interval_and_the_heap_together():
    from hybridgi_core import heap
    from hybridgi_core.rendering import rendering

    before = sys.getswitchinterval()
    tuned = heap._glibc() is not None
    with rendering():
        assert gil.holders() == 1 and heap.holders() == int(tuned)
        assert sys.getswitchinterval() == pytest.approx(gil.SWITCH_INTERVAL_S)
    assert gil.holders() == 0 and heap.holders() == 0 and sys.getswitchinterval() == pytest.approx(before)
