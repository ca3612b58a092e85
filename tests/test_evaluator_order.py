"""Rows in episode order after an evaluator restart (pure logic of the evaluator's choice).

The end-to-end check is tests/test_faults.py's evaluator kill: there the learner's
newest point reached the restarted evaluator before the resends of the points it had
missed, and the run's rows came out as 20, 40, 140, 60, ... before this ordering."""

from __future__ import annotations

import collections
import logging
import types

from services.evaluator import main as ev
from shared.net.messages import Weights
from shared.net.wire import decode, encode


def _msg(point: int, unreported: list[int]) -> Weights:
    return decode(_weights(point, unreported), Weights)


def test_the_earliest_pending_point_goes_first_whatever_the_arrival_order():
    pending = [_msg(140, []), _msg(80, []), _msg(60, [])]
    msg, missing = ev.earliest_point(pending, published={})
    assert msg.eval_point == 60 and missing == []


def test_a_point_waits_for_earlier_unreported_points_not_here_yet():
    pending = [_msg(140, [60, 80, 100, 120])]
    _, missing = ev.earliest_point(pending, published={20: 0.0, 40: 0.0})
    assert missing == [60, 80, 100, 120]
    # evaluated here already (the learner had not seen the row yet) or pending: no wait
    pending.append(_msg(60, []))
    msg, missing = ev.earliest_point(pending, published={80: 0.0, 100: 0.0})
    assert msg.eval_point == 60 and missing == []
    _, missing = ev.earliest_point([_msg(140, [60, 80, 120])], published={60: 0.0, 80: 0.0})
    assert missing == [120]


def test_a_point_naming_no_unreported_points_is_taken_at_once():
    # (A learner before wire schema 2 carried the list in its stats map; the codec
    # refuses its messages now: tests/test_wire.py.)
    msg, missing = ev.earliest_point([_msg(40, [])], published={})
    assert msg.eval_point == 40 and missing == []


def _service(pending: list[Weights], clock: list[float]) -> types.SimpleNamespace:
    """What next_point reads of the service, on the test's own clock."""
    st = types.SimpleNamespace(
        run="r", pending=collections.deque(pending), published={}, held_since=None
    )
    return types.SimpleNamespace(st=st, log=logging.getLogger("test"), clock=lambda: clock[0])


def test_next_point_holds_then_gives_up_after_the_order_wait():
    clock = [1000.0]
    svc = _service([_msg(140, [60])], clock)
    assert ev.EvaluatorService.next_point(svc, svc.st) is None  # held: 60 is on its way
    clock[0] += ev.ORDER_WAIT_S / 2
    assert ev.EvaluatorService.next_point(svc, svc.st) is None
    svc.st.pending.append(_msg(60, []))  # the resend arrives: it goes first, then 140
    assert ev.EvaluatorService.next_point(svc, svc.st).eval_point == 60
    svc.st.published[60] = clock[0]
    assert ev.EvaluatorService.next_point(svc, svc.st).eval_point == 140
    assert not svc.st.pending

    svc = _service([_msg(140, [60])], clock)  # 60 never comes: 140 is not held for ever
    assert ev.EvaluatorService.next_point(svc, svc.st) is None
    clock[0] += ev.ORDER_WAIT_S + 0.1
    assert ev.EvaluatorService.next_point(svc, svc.st).eval_point == 140


def _weights(point: int, unreported: list[int]) -> bytes:
    fields = dict(version=1, updates=0, env_steps=0, episodes=point, collisions_cum=0)
    return encode(
        Weights(
            "r",
            eval_point=point,
            actors=[],
            stats={},
            incarnation="l",
            unreported=unreported,
            **fields,
        )
    )


def _points(sent: list[bytes]) -> list[tuple[int, list[int]]]:
    return [(m.eval_point, m.unreported) for m in (decode(s, Weights) for s in sent)]


def _learner(unreported: dict[int, float], last_sent: int, reported_at: float):
    from services.learner.evaluations import EvaluationsInFlight
    from services.learner.outbound import Outbound

    ev = EvaluationsInFlight()
    ev.unreported = {p: (t, _weights(p, [20] if p > 20 else [])) for p, t in unreported.items()}
    ev.last_sent, ev.reported_at = last_sent, reported_at
    sent: list[bytes] = []
    outgoing = types.SimpleNamespace(eval_pub=sent.append)
    st = types.SimpleNamespace(run="r", evaluations=ev, outgoing=outgoing)
    out = Outbound("l", print, lambda: 0, lambda counter: [], logging.getLogger("test"))
    return out, st, sent


def test_the_learner_resends_a_point_the_evaluator_holds_later_ones_for_after_5_s():
    now = 1000.0
    # point 20 was lost; 40 went out after it, and the evaluator (holding 40) is silent
    out, st, sent = _learner({20: now - 6, 40: now - 6}, last_sent=40, reported_at=now - 6)
    out.resend(st, now)
    assert _points(sent) == [(20, [])]  # not 40: the newest point waits for the long rule
    # within 5 s of the evaluator's last report nothing is resent: it may just be busy
    out, st, sent = _learner({20: now - 6, 40: now - 6}, last_sent=40, reported_at=now - 3)
    out.resend(st, now)
    assert sent == []
    # the newest point alone is resent after 30 s of silence, as before
    out, st, sent = _learner({40: now - 31}, last_sent=40, reported_at=now - 31)
    out.resend(st, now)
    assert _points(sent) == [(40, [])]  # its list of when it first went out named 20,
    # whose row has come since: the resend no longer does


def test_a_resend_at_once_names_only_the_points_still_without_a_row():
    now = 1000.0
    out, st, sent = _learner({20: now - 1, 40: now - 1}, last_sent=40, reported_at=now - 1)
    out.resend(st, now, at_once=True)
    assert _points(sent) == [(20, []), (40, [20])]
