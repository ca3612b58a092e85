"""The services' stats as typed values: each publishes the map it published before
(same keys, same order, same values), and a reader reads an older or partial map with
0 for what it lacks and every value as it came (rows made from them do not change)."""

from __future__ import annotations

import json

from shared.net.stats import ActorStats, CounterStats, LearnerStats

LEARNER_MAP = {  # a learner's stats map as run_stats made it before the types
    "updates": 40,
    "ingested": 500,
    "episodes_ingested": 20,
    "replay_ratio": 1.0,
    "policy_lag": 0.5,
    "policy_version": 20,
    "wall_s": 3.25,
    "steps_per_sec": 153.8,
    "updates_per_sec": 12.3,
    "backlog": 0,
    "window_open": True,
    "bonus_p50_ms": 1.5,
    "bonus_p99_ms": 4.0,
    "bonus_wait_ms_per_update": 0.7,
    "bonus_queries": 40,
    "bonus_rows_per_query": 1024.0,
    "bonus_failures": 0,
    "bonus_unanswered": 1,
    "bonus_refused": 2,
    "bonus_mean": 0.3,
    "rejects_total": 0,
    "contended_updates": 2,
    "eval_rows_seen": 2,
    "cuts": 1,
    "cut_ms_mean": 30.0,
    "cut_bytes": 4096,
    "ms_per_update_sample": 1.0,
    "ms_per_update_bonus_wait": 0.7,
    "ms_per_update_other": 0.2,
    "critic_loss": 0.01,  # the algorithm's own
    "contended_updates_tuned": 1.0,
}


def test_learner_stats_give_back_the_map_they_were_read_from_key_for_key():
    s = LearnerStats.from_wire(LEARNER_MAP)
    assert s.spent == {"sample": 1.0, "bonus_wait": 0.7, "other": 0.2}
    assert s.own == {"critic_loss": 0.01, "contended_updates_tuned": 1.0}
    assert list(s.to_wire().items()) == list(LEARNER_MAP.items())
    assert s.counter is None and s.tables == CounterStats()


def test_the_algorithms_own_stat_takes_precedence_in_place():
    s = LearnerStats(contended_updates=2, own={"contended_updates": 5, "q": 1.0})
    wire = s.to_wire()
    assert wire["contended_updates"] == 5 and list(wire)[-1] == "q"
    assert LearnerStats.from_wire(wire).to_wire() == wire


def test_a_weights_stats_carry_the_counters_and_the_bonuss_as_given():
    given = {"table_size": 7, "count1_pct": 12.5, "counted_transitions": 300, "acked": {"a0": 3}}
    s = LearnerStats(updates=3, counter=given, bonus={"bonus_std": 0.1})
    wire = s.to_wire()
    assert wire["counter"] == given and list(wire)[-2:] == ["counter", "bonus"]
    back = LearnerStats.from_wire(json.loads(json.dumps(wire)))
    assert (back.tables.table_size, back.tables.count1_pct, back.tables.queries) == (7, 12.5, 0)
    assert back.bonus_stat("bonus_std") == 0.1 and back.bonus_stat("bonus_mean") == 0.0
    between = LearnerStats(counter={}, bonus={}).to_wire()
    assert between["counter"] == {} and between["bonus"] == {}


def test_an_older_or_partial_map_reads_what_it_lacks_as_0_and_the_rest_as_it_came():
    s = LearnerStats.from_wire({"steps_per_sec": 3, "wall_s": None})
    assert s.steps_per_sec == 3 and isinstance(s.steps_per_sec, int)  # (not made a float)
    assert s.wall_s is None and s.replay_ratio == 0.0 and s.episodes_ingested == 0


def test_an_actors_stats_name_the_group_only_in_a_group():
    alone = ActorStats(rank=1, episodes=2, published=50).to_wire()
    assert "group" not in alone and list(alone)[:3] == ["rank", "episodes", "published"]
    grouped = ActorStats(rank=0, group=4).to_wire()
    assert list(grouped)[-1] == "group" and grouped["group"] == 4
    assert ActorStats.from_wire(grouped) == ActorStats(rank=0, group=4)


def test_a_counters_stats_round_trip_and_ignore_keys_they_do_not_know():
    c = CounterStats(table_size=9, counted_transitions=40, snapshots=1)
    assert CounterStats.from_wire({**c.to_wire(), "acked": {"a0": 40}}) == c
    assert list(c.to_wire())[:3] == ["table_size", "count1_pct", "counted_transitions"]
