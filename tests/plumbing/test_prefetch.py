"""plumbing.prefetch: results in the items' order, an error where its item is taken, and never
more than `ahead` + 1 results alive (the memory bound a calibration relies on: a pose's frames
are hundreds of MB at 24 MP)."""

from __future__ import annotations

import threading
import time

import pytest

from plumbing.prefetch import prefetched


class _Frame:
    """A result that counts how many of its kind are alive."""

    alive = 0
    most = 0
    lock = threading.Lock()

    def __init__(self, k: int) -> None:
        self.k = k
        with _Frame.lock:
            _Frame.alive += 1
            _Frame.most = max(_Frame.most, _Frame.alive)

    def __del__(self) -> None:
        with _Frame.lock:
            _Frame.alive -= 1


def _decode(k: int) -> _Frame:
    time.sleep(0.002 * (k % 3))  # uneven work: later items may finish first
    return _Frame(k)


@pytest.mark.parametrize("ahead", [1, 2, 3])
def test_results_come_in_order_and_at_most_ahead_plus_one_are_alive(ahead: int) -> None:
    _Frame.alive = _Frame.most = 0
    seen = []
    for frame in prefetched(_decode, range(20), ahead=ahead):
        seen.append(frame.k)
        time.sleep(0.003)  # the caller's work: the workers run ahead meanwhile
        del frame
    assert seen == list(range(20))
    # The bound, and that the workers did run ahead (one result held while another was made).
    assert 2 <= _Frame.most <= ahead + 1
    assert _Frame.alive == 0


def test_an_error_is_raised_where_its_item_is_taken() -> None:
    def decode(k: int) -> int:
        if k == 3:
            raise ValueError("frame 3 is truncated")
        return k

    seen = []
    with pytest.raises(ValueError, match="frame 3"):
        for k in prefetched(decode, range(6), ahead=2):
            seen.append(k)
    assert seen == [0, 1, 2]


def test_no_items_is_no_results() -> None:
    assert list(prefetched(_decode, [])) == []
