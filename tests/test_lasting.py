"""rig.lasting: when a lasting, changing condition is said, by the caller's clock (pure)."""

from rig.lasting import LastingCondition


def test_a_condition_flipping_at_every_event_is_said_in_a_bounded_number_of_lines():
    # A link failing every other write, 10 events a second for 10 minutes: 6000 changes. Four are
    # said at once (the burst), then one line a minute sums up the changes since.
    cond = LastingCondition(None, burst=4, refill_s=60.0)
    said = [(t, line) for k in range(6000)
            if (line := cond.update("failing" if k % 2 else None, t := k * 0.1)) is not None]
    assert [line.kind for _, line in said[:4]] == ["change"] * 4
    summaries = said[4:]
    assert len(summaries) == int(599.9 // 60.0)  # one a minute, after the burst, within the 600 s
    assert all(59.5 <= b[0] - a[0] <= 60.5 for a, b in zip(said[3:], summaries, strict=False))
    # Each sums up the changes since its `since_s` (every event there is one) and counts each event,
    # its own too: "N changes in T s" is true of every line. (The first says the state it changed to.)
    for t, line in summaries:
        assert line.budget_spent and line.changes == round((t - line.since_s) / 0.1) > 590, (t, line)
        assert sum(line.counts.values()) == line.changes + 1, (t, line)
    assert [line.kind for _, line in summaries[1:]] == ["still"] * (len(summaries) - 1)


def test_two_real_changes_are_each_said_at_once_with_the_counts_of_the_stretch_before():
    cond = LastingCondition(None, burst=4, refill_s=60.0)
    for k in range(100):
        assert cond.update(None, float(k), "written") is None  # the ok state is never said
    first = cond.update("failing", 100.0, "write_errors")
    assert first is not None and first.changes == 1
    assert (first.kind, first.state, first.before) == ("change", "failing", None)
    for k in range(1, 50):
        assert cond.update("failing", 100.0 + k, "write_errors") is None
    back = cond.update(None, 150.0, "written")
    assert back is not None and (back.kind, back.state, back.before) == ("change", None, "failing")
    assert back.since_s == 100.0 and back.counts == {"write_errors": 50, "written": 1}


def test_a_lasting_bad_state_is_said_again_at_doubling_intervals_up_to_the_cap():
    cond = LastingCondition(None, remind_s=60.0, remind_max_s=240.0)
    said_at = [t for t in range(0, 1200)
               if cond.update("failing" if t else None, float(t)) is not None]
    # Said when it starts (t=1), then after 60, 120, 240, 240, ... seconds.
    assert said_at[:6] == [1, 61, 181, 421, 661, 901]


def test_time_that_steps_back_neither_refills_the_budget_nor_delays_a_reminder():
    # A replayed log's clock may step back (a second log, a looped file): no crash, no burst of lines.
    cond = LastingCondition(None, burst=1, refill_s=60.0, remind_s=30.0)
    assert cond.update("dark", 1000.0) is not None  # the one token
    assert cond.update(None, 1001.0) is None  # no token left: counted, not said
    assert cond.update("dark", 5.0) is None  # stepped back 996 s: still no token
    still = cond.update("dark", 35.0)  # the reminder comes 30 s after the step back, not at 1030
    assert still is not None and still.kind == "still" and still.state == "dark"


def test_an_event_throttle_says_the_first_event_then_one_a_period_with_the_count_since():
    from rig.lasting import EventThrottle

    throttle = EventThrottle(60.0)
    assert throttle.note(0.0) == (1, None)  # the first, at once
    assert [throttle.note(t) for t in (10.0, 20.0, 59.9)] == [None, None, None]
    assert throttle.note(60.0) == (4, 0.0)  # three unsaid and this one, since the line at 0 s
    assert throttle.note(61.0) is None
    assert throttle.note(200.0) == (2, 60.0)
