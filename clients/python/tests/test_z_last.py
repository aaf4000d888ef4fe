"""Last (files run in name order): starting a trade-off computation keeps the
daemon's CPU busy for minutes, so nothing runs on this daemon after it."""

from __future__ import annotations

import pytest
from conftest import settle

from rigd_client import Client, RigdError


def test_start_tradeoff(client: Client) -> None:
    settle(client)
    with pytest.raises(RigdError) as e:
        client.start_tradeoff("no-such-scene")
    assert e.value.status == 422 and "corduroy" in e.value.detail
    started = client.start_tradeoff("flat-calibration", texture=4, held_out=1, render_size=(16, 16))
    assert started == {"scene": "flat-calibration", "texture": 4, "held_out": 1, "render_size": [16, 16]}
    with pytest.raises(RigdError) as e:
        client.start_tradeoff()
    assert e.value.status == 409
