"""What a watcher draws of the results it hears: those its campaign names as accepted, whichever comes first, and
all of them from a lab that names none."""

from twin.core.messages import Kind, decode, fingerprint, kept, pack
from twin.view.vouched import MAX_KEPT, Vouched


def result(i: int) -> bytes:
    return pack(Kind.RESULT, {"outputs": {"peak_nm": float(i)}, "sample": None}, id=f"spectrometer-1:{i}",
                sender="spectrometer-1", t_lab=60.0, campaign="c1", task=f"e{i}s1", attempt=1, token="a" * 32)


def decisions(accepted: list[str] | None) -> bytes:
    detail = {"items": []} if accepted is None else {"items": [], "accepted": accepted}
    return pack(Kind.DECISION, {"what": "decisions", "detail": detail}, id="orchestrator:b1", sender="orchestrator",
                t_lab=60.0, campaign="c1")


def name_of(payload: bytes) -> str:
    env, _ = decode(payload)
    return fingerprint(kept(env, payload))


def test_a_result_is_drawn_once_named_before_or_after_it_is_heard_and_one_never_named_is_not():
    fed: list[bytes] = []
    watch = Vouched(lambda key, payload: fed.append(payload))
    first, second, forged = result(1), result(2), result(3)
    watch("evt", first)
    watch("evt", forged)
    assert fed == []  # heard, not yet named
    said = decisions([name_of(first)])
    watch("decisions", said)
    assert fed == [first, said]  # the result before the decisions that name it, as the journal has them
    watch("decisions", decisions([name_of(second)]))
    watch("evt", second)  # named first: drawn as it comes
    assert fed[-1] == second and forged not in fed
    assert b'"token"' in first and b'"token"' not in kept(decode(first)[0], first)  # named less its token


def test_a_lab_that_names_nothing_has_its_results_drawn_and_unnamed_ones_are_forgotten_past_the_bound():
    fed: list[bytes] = []
    watch = Vouched(lambda key, payload: fed.append(payload))
    waiting = result(1)
    watch("evt", waiting)
    watch("decisions", decisions(None))  # an older lab: no accepted at all
    watch("evt", result(2))
    assert fed[0] == waiting and fed[-1] == result(2)
    drawn: list[bytes] = []
    flood = Vouched(lambda key, payload: drawn.append(payload))
    for i in range(MAX_KEPT + 5):  # results never named: a forger's flood
        flood("evt", result(10 + i))
    oldest, newest = result(10), result(10 + MAX_KEPT + 4)
    flood("decisions", decisions([name_of(oldest), name_of(newest)]))
    assert drawn[:-1] == [newest]  # the oldest was forgotten; the decisions message follows


def test_a_result_that_fails_validation_is_never_drawn_and_what_is_not_a_message_passes_on():
    fed: list[bytes] = []
    watch = Vouched(lambda key, payload: fed.append(payload))
    broken = result(1).replace(b'"t_lab":60.0', b'"t_lab":"soon"')  # JSON, a result, but not a valid message
    assert broken != result(1)
    watch("evt", broken)
    watch("decisions", decisions(None))
    watch("evt", broken)  # not from a lab that names nothing either
    watch("evt", b"not json, mentions a result")
    assert broken not in fed and fed[-1] == b"not json, mentions a result"


def test_a_decisions_message_without_names_does_not_turn_off_the_naming_of_a_lab_that_names():
    """One forged decisions message without `accepted` (anyone can publish one on a bus without security) made the
    watcher take the lab for an older one and draw everything after it, forged results included."""
    fed: list[bytes] = []
    watch = Vouched(lambda key, payload: fed.append(payload))
    watch("decisions", decisions([]))
    watch("decisions", decisions(None))  # the forger's
    forged = result(3)
    watch("evt", forged)
    assert forged not in fed
    older: list[bytes] = []
    lab = Vouched(lambda key, payload: older.append(payload))
    lab("decisions", decisions(None))  # an older lab, or a forger first ...
    lab("decisions", decisions([]))  # ... until the lab names: held again from then on
    lab("evt", forged)
    assert forged not in older
