"""``GET /runs`` paging and filters (limit, cursor/next, total, sample, state,
plan, profile, from, to), and its refusals."""

from __future__ import annotations

from typing import List

import pytest
from conftest import settle

from rigd_client import Client, RigdError, RunView

SAMPLES = [f"pg-{i}" for i in range(5)]
PLAN = "pgplan"


@pytest.fixture(scope="module")
def paged(client: Client) -> List[RunView]:
    """Five tiny runs of the plan ``pgplan``, plus whatever ran before; newest first."""
    settle(client)
    plan = {"name": PLAN, "directions": [{"theta_deg": 0, "phi_deg": 0}]}
    for s in SAMPLES:
        run = client.start_run(s, plan, frame_size=(32, 24))
        assert client.wait(run, timeout=60)["state"] == "completed"
    return [r for r in client.iter_runs(limit=1000)]


def test_limit_next_and_total(client: Client, paged: List[RunView]) -> None:
    page = client.runs(limit=2)
    assert len(page.runs) == 2 and page.next is not None
    assert page.total == len(paged)
    assert [r["id"] for r in page.runs] == [r["id"] for r in paged[:2]]
    second = client.runs(limit=2, cursor=page.next)
    assert [r["id"] for r in second.runs] == [r["id"] for r in paged[2:4]]


def test_iter_runs_follows_cursors(client: Client, paged: List[RunView]) -> None:
    for size in (1, 2, 3):
        ids = [r["id"] for r in client.iter_runs(limit=size)]
        assert ids == [r["id"] for r in paged], f"page size {size}"
    starts = [r["started_at"] for r in paged]
    assert starts == sorted(starts, reverse=True)  # newest first
    last = client.runs(limit=len(paged))
    assert last.next is None


def test_filters(client: Client, paged: List[RunView]) -> None:
    (one,) = client.runs(sample="pg-3").runs
    assert one["sample"] == "pg-3"
    ours = client.runs(plan=PLAN)
    assert sorted(r["sample"] for r in ours.runs) == SAMPLES and ours.total == 5
    assert [r["sample"] for r in client.iter_runs(limit=2, plan=PLAN)] == SAMPLES[::-1]
    assert all(r["state"] == "completed" for r in client.iter_runs(state="completed"))
    aborted = [r["id"] for r in paged if r["state"] == "aborted"]
    assert [r["id"] for r in client.iter_runs(state="aborted")] == aborted
    assert len(list(client.iter_runs(profile="bonn-gonioreflectometer"))) == len(paged)
    assert list(client.iter_runs(profile="no-such-profile")) == []


def test_time_window(client: Client, paged: List[RunView]) -> None:
    ours = [r for r in paged if r["plan"] == PLAN]
    t0 = min(r["started_at"] for r in ours)
    t1 = max(r["started_at"] for r in ours)
    since = list(client.iter_runs(from_=t0))
    assert since and all(r["started_at"] >= t0 for r in since)
    assert {r["id"] for r in ours} <= {r["id"] for r in since}
    until = list(client.iter_runs(to=t1))
    assert all(r["started_at"] <= t1 for r in until)
    window = list(client.iter_runs(from_=t0, to=t1, plan=PLAN))
    assert sorted(r["sample"] for r in window) == SAMPLES


@pytest.mark.parametrize("query", [
    {"limit": 0}, {"limit": 10**9}, {"cursor": "not-a-cursor"}, {"state": "sleeping"},
    {"from_": "yesterday"}, {"to": "2026-13-45"},
])
def test_bad_queries_are_refused_with_the_reason(client: Client, query: dict) -> None:
    with pytest.raises(RigdError) as refused:
        client.runs(**query)
    assert refused.value.status == 400, refused.value
    assert refused.value.detail, refused.value
