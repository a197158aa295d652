"""What C decoders print goes into a frame's error message (calibration.decode redirects file
descriptor 2 while a frame decodes) — and the redirection is safe when frames decode on several
threads at once (plumbing.prefetch): two overlapping decodes once restored fd 2 in the wrong
order and left it on a deleted temp file, so `gonio calibrate`'s one-line error vanished (exit 2,
empty stderr: tests/calibration/test_frame_integrity.py, twice in fresh clones)."""

from __future__ import annotations

import os
import threading

from calibration.decode import _native_stderr


def _fd2() -> tuple[int, int]:
    st = os.fstat(2)
    return st.st_dev, st.st_ino


def test_overlapping_decodes_give_fd2_back_and_keep_their_own_text() -> None:
    before = _fd2()
    first_in, second_in, first_out = threading.Event(), threading.Event(), threading.Event()
    said: dict[str, list[str]] = {"a": [], "b": []}

    def first() -> None:  # enters first, leaves first: the order that broke fd 2
        with _native_stderr(said["a"]):
            os.write(2, b"libraw: a says hello\n")
            first_in.set()
            second_in.wait(10)
        first_out.set()

    def second() -> None:
        first_in.wait(10)
        with _native_stderr(said["b"]):
            second_in.set()
            first_out.wait(10)
            os.write(2, b"openexr: b says hello\n")

    threads = [threading.Thread(target=first), threading.Thread(target=second)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(10)
    assert _fd2() == before  # stderr is the process's own again
    assert "a says hello" in "".join(said["a"])
    assert "b says hello" in "".join(said["b"])  # b's text, whatever a saw of it
