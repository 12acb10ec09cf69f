from tissue_common.throttle import EventThrottle


def test_each_kind_is_logged_at_most_once_per_period_and_every_event_is_counted():
    t = EventThrottle()
    assert t.event('nan', 0.0, 1.0) == 1            # the first one is always logged
    assert t.event('nan', 0.5, 1.0) is None
    assert t.event('frame', 0.6, 1.0) == 1          # another kind has its own period
    assert t.event('nan', 0.99, 1.0) is None
    assert t.event('nan', 1.0, 1.0) == 4            # a period later, with the count so far
    assert t.counts == {'nan': 4, 'frame': 1}
