"""The garbage collector during a paced drive (vcfusion.hitl.gcpause): the heap frozen for the
block and given back on every exit, and each collection timed."""

import gc

import pytest

from vcfusion.hitl.gcpause import GcPauses, frozen_heap


class Cycle:
    def __init__(self):
        self.me = self


def test_the_heap_is_frozen_in_the_block_and_unfrozen_after_it_even_on_an_error():
    assert gc.get_freeze_count() == 0
    with frozen_heap():
        assert gc.get_freeze_count() > 0
    assert gc.get_freeze_count() == 0
    with pytest.raises(RuntimeError), frozen_heap():
        assert gc.get_freeze_count() > 0
        raise RuntimeError("the trip failed")
    assert gc.get_freeze_count() == 0


def test_a_full_collection_in_the_block_skips_the_frozen_heap():
    # cycles made before the block are frozen: a full collection inside does not free them; the
    # block's own garbage it does
    import weakref

    before = Cycle()
    ref_before = weakref.ref(before)
    del before
    with frozen_heap():
        # frozen_heap collected first: the cycle made before it is gone already
        assert ref_before() is None
        kept = Cycle()  # alive when frozen below (nested freeze keeps it frozen until the outer exit)
        ref_kept = weakref.ref(kept)
        with frozen_heap():
            del kept
            gc.collect()
            assert ref_kept() is not None  # frozen: not collected although unreachable
            inner = Cycle()
            ref_inner = weakref.ref(inner)
            del inner
            gc.collect()
            assert ref_inner() is None  # made in the block: collected
        assert gc.get_freeze_count() > 0  # the outer block's freeze holds
    assert gc.get_freeze_count() == 0
    gc.collect()
    assert ref_kept() is None  # unfrozen at the outer exit: collected again


def test_the_pauses_are_timed_by_generation_while_entered_only():
    pauses = GcPauses()
    with pauses:
        gc.collect(0)
        gc.collect(2)
    assert [p[0] for p in pauses.pauses] == [0, 2]
    assert all(p[2] >= 0.0 for p in pauses.pauses) and pauses.total_s == pytest.approx(sum(p[2] for p in pauses.pauses))
    assert pauses.since(pauses.pauses[1][1]) == pauses.pauses[1:]
    assert pauses._callback not in gc.callbacks
    gc.collect()
    assert len(pauses.pauses) == 2  # no longer timed
