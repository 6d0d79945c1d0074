"""Tests of the compiled programs' machinery (``jcomps.programs``)."""

import time

from jcomps import programs


def test_a_long_compile_keeps_saying_so():
    beats = []
    with programs._heartbeat(lambda: beats.append(1), interval=0.05):
        time.sleep(0.3)
    count = len(beats)
    time.sleep(0.15)
    assert count >= 2 and len(beats) == count  # beats while the block runs, none after
