"""Issue 32: devices that appear while an edge runs are bounded per edge (``--max-devices``), so are its liveliness
tokens; a new id beyond the bound is dropped and counted in the status, the devices already there are unaffected."""

from __future__ import annotations

import numpy as np
import pytest

from magnet import wire
from services.edge.service import EdgeStatus, Publisher
from services.edge.settings import EdgeSettings


class FakeToken:
    def __init__(self, tokens: list[str], key: str) -> None:
        self.tokens, self.key = tokens, key
        tokens.append(key)

    def undeclare(self) -> None:
        self.tokens.remove(self.key)


class FakeSession:
    def __init__(self) -> None:
        self.tokens: list[str] = []
        self.puts: list[str] = []

    def liveliness(self) -> FakeSession:
        return self

    def declare_token(self, key: str) -> FakeToken:
        return FakeToken(self.tokens, key)

    def put(self, key: str, payload: bytes, **_: object) -> None:
        self.puts.append(key)


def batch(device: str) -> wire.RawBatch:
    return wire.RawBatch(device, 0, "mavlink", np.array([1_000], dtype=np.int64), np.array([[20.0, 0.0, 40.0]]))


def test_devices_appearing_beyond_max_devices_are_dropped_and_counted() -> None:
    settings = EdgeSettings(mavlink="udpin:127.0.0.1:14550", max_devices=3, device="e1")
    status = EdgeStatus(settings)
    session = FakeSession()
    status.open(session)  # type: ignore[arg-type]
    publisher = Publisher(session, settings, status)  # type: ignore[arg-type]
    flood = [f"mav{k}-mag0" for k in range(1, 201)]
    for device in flood:
        status.device_seen(device)
        status.device_health(device, False)
    publisher.put([batch(d) for d in flood])
    admitted = {"e1", "mav1-mag0", "mav2-mag0", "mav3-mag0"}
    assert status.admitted == admitted
    device_tokens = [t for t in session.tokens if not t.endswith("/unhealthy")]
    assert len(device_tokens) == 3 and len(session.tokens) == 6  # alive + unhealthy of each admitted device only
    assert {k.split("/")[1] for k in session.puts} == admitted - {"e1"}
    assert status.as_dict()["dropped"] == {"devices:limit": 197}
    publisher.put([batch("mav1-mag0"), batch("mav999-mag0")])  # the admitted go on, any new one is dropped
    assert session.puts[-1] == "magnet/mav1-mag0/raw" and status.as_dict()["dropped"] == {"devices:limit": 198}
    status.close()
    assert session.tokens == []


def test_the_limits_are_options_with_sane_defaults() -> None:
    settings = EdgeSettings(mavlink="udpin:127.0.0.1:14550")
    assert settings.max_devices == 256 and settings.max_port_devices == 64
    with pytest.raises(ValueError, match="--max-devices"):
        EdgeSettings(mavlink="udpin:127.0.0.1:14550", max_devices=0)
    with pytest.raises(ValueError, match="--max-port-devices"):
        EdgeSettings(mavlink="udpin:127.0.0.1:14550", max_port_devices=0)


def test_a_forgotten_device_frees_its_place_and_tokens_for_a_new_one() -> None:
    """Issue 32: a flood's ids filled the edge's places and kept a real vehicle that came later out until the edge
    restarted. A device its source forgot (silent ``--forget-after``) gives its tokens and its place back; a device
    the edge started with is never forgotten."""
    settings = EdgeSettings(mavlink="udpin:127.0.0.1:14550", max_devices=3, device="e1")
    status = EdgeStatus(settings)
    session = FakeSession()
    status.open(session)  # type: ignore[arg-type]
    publisher = Publisher(session, settings, status)  # type: ignore[arg-type]
    flood = [f"mav{k}-mag0" for k in range(2, 12)]
    for device in flood:
        status.device_seen(device)
        status.device_health(device, False)
    publisher.put([batch(d) for d in flood])
    publisher.put([batch("mav1-mag1")])  # the real vehicle, after the flood: no place
    assert "magnet/mav1-mag1/raw" not in session.puts and status.as_dict()["dropped"] == {"devices:limit": 8}
    for device in flood:  # the flood falls silent: its source forgets its ids
        status.device_gone(device)
    status.device_gone("e1")
    assert session.tokens == [] and status.admitted == {"e1"} and status.as_dict()["forgotten"] == 3
    status.device_seen("mav1-mag1")
    publisher.put([batch("mav1-mag1")])
    assert session.puts[-1] == "magnet/mav1-mag1/raw" and session.tokens == ["magnet/@alive/device/mav1-mag1"]
    assert status.admitted == {"e1", "mav1-mag1"} and set(status.keys) == {"e1", "mav1-mag1"}
    assert EdgeSettings(mavlink="udpin:127.0.0.1:14550").forget_after_s == 60.0
    with pytest.raises(ValueError, match="--forget-after"):
        EdgeSettings(mavlink="udpin:127.0.0.1:14550", forget_after_s=0.0)
