"""A gateway's choice of the one service it serves a board name from
(service/net/board_claims.py), on made-up instances and times."""
from service.net.board_claims import FORGET_GONE_S, LOST_AFTER_S, BoardClaims

A, B, C = "arm-pc:101:aaaaaa", "hand-pc:202:bbbbbb", "arm-pc:303:cccccc"


def test_the_first_service_heard_is_served_and_another_of_its_name_refused_and_reported():
    claims = BoardClaims()
    assert claims.heard("arm", A, 0.0, alive=True)
    assert not claims.heard("arm", B, 0.1, alive=True)
    served = [claims.heard("arm", instance, 0.2 + i * 1e-3) for i, instance in enumerate([A, B] * 5)]
    assert served == [True, False] * 5
    assert claims.heard("hand", B, 0.3)  # another name: B's own
    report = claims.report("arm", 0.5)
    assert report["publisher"] == A
    assert [(p["instance"], p["served"], p["samples_refused"]) for p in report["publishers"]] == \
        [(A, True, 0), (B, False, 5)]
    [problem] = report["problems"]
    assert A in problem and B in problem and "--source NAME=URL" in problem and "gone" not in problem


def test_the_refused_service_s_death_is_reported_and_forgotten_after_a_while():
    claims = BoardClaims()
    claims.heard("arm", A, 0.0, alive=True)
    claims.heard("arm", B, 0.0, alive=True)
    assert not claims.heard("arm", B, 1.0, alive=False)  # not the served one's: the board is not told
    claims.heard("arm", A, 2.9)
    report = claims.report("arm", 3.0)
    assert "is gone (its liveliness token went, 2.0 s ago)" in report["problems"][0]
    assert [p["gone_for_s"] for p in report["publishers"]] == [None, 2.0]
    claims.heard("arm", A, FORGET_GONE_S)
    assert claims.report("arm", FORGET_GONE_S + 0.5)["problems"]
    claims.heard("arm", A, FORGET_GONE_S + 1.5)
    assert claims.report("arm", FORGET_GONE_S + 1.5) == {
        "publisher": A, "problems": [], "publishers": [{"instance": A, "served": True, "alive": True,
                                                         "last_heard_age_s": 0.0, "gone_for_s": None,
                                                         "samples_refused": 0}]}


def test_a_restarted_service_takes_the_name_but_one_that_was_refused_never_does():
    claims = BoardClaims()
    claims.heard("arm", A, 0.0, alive=True)
    claims.heard("arm", B, 0.5)  # refused while A lives
    assert claims.heard("arm", A, 1.0, alive=False)  # the served one's death: told to the board
    assert not claims.heard("arm", B, 1.1)  # B does not slip in
    assert claims.heard("arm", C, 2.0, alive=True)  # A restarted as C: served
    assert claims.report("arm", 2.0)["publisher"] == C
    assert not claims.heard("arm", A, 2.1)  # a late sample of A, after C took over


def test_a_silent_service_without_a_token_change_releases_its_name_after_the_lost_delay():
    claims = BoardClaims()
    claims.heard("arm", A, 0.0, alive=True)
    assert not claims.heard("arm", C, LOST_AFTER_S - 0.1)  # A still counts: heard within the delay
    claims2 = BoardClaims()
    claims2.heard("arm", A, 0.0, alive=True)
    assert claims2.heard("arm", C, LOST_AFTER_S + 0.1)


def test_a_client_s_claims_hand_the_name_to_a_live_refused_service_once_the_holder_is_gone():
    claims = BoardClaims(hand_over=True)
    claims.heard("arm", A, 0.0, alive=True)
    claims.heard("arm", B, 0.1, alive=True)
    claims.heard("arm", C, 0.2, alive=True)
    assert not claims.heard("arm", B, 0.5) and claims.holder("arm") == A
    claims.heard("arm", C, 0.9, alive=False)  # C went while refused: it never takes the name
    assert claims.heard("arm", A, 1.0, alive=False)
    assert not claims.heard("arm", C, 1.05)  # a late sample of C, gone
    assert claims.heard("arm", B, 1.1) and claims.holder("arm") == B
    assert not claims.heard("arm", A, 1.2)  # a late sample of A, after B took over
    report = claims.report("arm", 1.2)
    assert report["publisher"] == B and [p["instance"] for p in report["publishers"] if p["served"]] == [B]
    assert [(p["instance"], p["samples_refused"]) for p in report["publishers"]] == [(A, 1), (B, 1), (C, 1)]


def test_a_service_restarted_on_its_host_before_its_predecessor_is_declared_gone_takes_the_name():
    """The new process heard 1 s after the old one's last sample, its token
    withdrawn only later (a lease expiring): it was refused for good, the
    board lost at the gateway. One from another host stays refused."""
    claims = BoardClaims()
    claims.heard("arm", A, 0.0)
    assert not claims.heard("arm", C, 1.0, alive=True)  # A's host, A not yet gone
    assert not claims.heard("arm", B, 1.1, alive=True)  # another host
    claims.heard("arm", A, 1.2, alive=False)
    assert claims.heard("arm", C, 2.0) and claims.report("arm", 2.0)["publisher"] == C
    assert not claims.heard("arm", B, 2.1)
    clash = BoardClaims()  # two services of one name on one host: the holder published on after the other came
    clash.heard("arm", A, 0.0, alive=True)
    clash.heard("arm", C, 1.0, alive=True)
    clash.heard("arm", A, 1.5)
    clash.heard("arm", A, 1.6, alive=False)
    assert not clash.heard("arm", C, 2.0)


def test_forgetting_a_name_keeps_a_live_refused_service_refused():
    """The gateway forgets a board lost for a minute: its holder and the
    services gone go, a refused one still alive stays refused. Before, every
    publisher went and the refused one took the name at its next sample."""
    claims = BoardClaims()
    claims.heard("arm", A, 0.0, alive=True)
    claims.heard("arm", B, 0.1, alive=True)  # refused: another host
    claims.heard("arm", C, 0.2, alive=True)  # refused, then gone
    claims.heard("arm", C, 0.3, alive=False)
    claims.heard("arm", A, 1.0, alive=False)
    claims.heard("arm", B, 60.5)  # B publishes on
    claims.forget("arm", 61.0)
    assert not claims.heard("arm", B, 62.0)
    report = claims.report("arm", 62.0)
    assert report["publisher"] is None
    assert [(p["instance"], p["served"]) for p in report["publishers"]] == [(B, False)]
    assert claims.heard("arm", "arm-pc:404:dddddd", 63.0, alive=True)  # A restarted: served


def test_the_liveliness_told_is_the_served_instance_s():
    claims = BoardClaims()
    assert claims.liveliness("arm") is None  # none served
    claims.heard("arm", A, 0.0, alive=True)
    claims.heard("arm", C, 1.0, alive=True)  # A's successor, refused while A lives
    assert claims.liveliness("arm") is True
    claims.heard("arm", A, 1.1, alive=False)
    assert claims.liveliness("arm") is False
    assert claims.heard("arm", C, 1.2) and claims.liveliness("arm") is True  # C's token, heard while refused
    other = BoardClaims()
    other.heard("arm", A, 0.0, alive=True)
    other.heard("arm", A, 1.0, alive=False)
    assert other.heard("arm", C, 1.5) and other.liveliness("arm") is None  # C's token not heard
