"""A board another host's service reads, as a gateway holds it: its frames as
they arrive over Zenoh, its last health document, and whether it is alive.

It answers the API's questions of a board (board.py) from what came over the
network; changes (tare, calibration) belong to the service that reads it and
are refused naming it. A board is ``lost`` when its service's liveliness
token goes (the session ended: a stopped or killed service is seen at once),
or when neither frames nor health came for ``LOST_AFTER_S`` (a network that
went silent, before Zenoh's lease expires); ``lost_since`` says since when
(the gateway forgets a board lost for a while). Liveliness and data are the
served service's only (``publishers``: net/board_claims.py), so another
service of the same name neither keeps it alive nor feeds it; when the name
passes to a successor, the gateway gives the board the successor's token.
"""
from __future__ import annotations

from typing import Callable

from .board import RemoteBoardError
from .history import Histories
from .pipeline import RateMeter, keep
from .reconstruct import ForceFrame

LOST_AFTER_S = 2.5  # health comes every second: two missed and a half
BOARD_FIELDS = ("link", "level", "stream", "rejected", "board_errors", "reconstruction", "clock", "replay")


class RemoteBoard:
    def __init__(self, name: str, histories: Histories, publishers: Callable[[float], dict] | None = None) -> None:
        """``publishers(now)``: the services publishing this name (BoardClaims.report)."""
        self.name = name
        self.publishers = publishers
        self.source = f"zenoh:tactile/{name}"
        self.sensors: dict = {}
        self.latest: dict[int, ForceFrame] = {}
        self.history = histories
        self.rates: dict[int, RateMeter] = {}
        self.health_document: dict | None = None
        self.health_at: float | None = None
        self.frame_at: float | None = None
        self.alive: bool | None = None  # None: no liveliness heard yet
        self.alive_at: float | None = None  # its token last declared
        self.lost_at: float | None = None

    @property
    def info(self) -> dict:
        return (self.health_document or {}).get("info") or {}

    def receive(self, frames: list[ForceFrame], now: float) -> None:
        """A batch of this board's frames (on the event loop)."""
        for frame in frames:
            self.sensors[frame.sensor.id] = frame.sensor
        keep(frames, self.latest, self.history, self.rates, now)
        self.frame_at = now
        if self.alive is not False:
            self.lost_at = None

    def on_health(self, document: dict, now: float) -> None:
        self.health_document, self.health_at = document, now

    def on_alive(self, alive: bool | None, now: float) -> None:
        """Its service's token declared (True) or withdrawn (False); None: the
        name passed to a service whose token was not heard (silence decides)."""
        self.alive = alive
        self.lost_at = now if alive is False else None
        if alive:
            self.alive_at = now

    def lost(self, now: float) -> bool:
        return self.lost_since(now) is not None

    def lost_since(self, now: float) -> float | None:
        """When the board was lost (s, the clock of ``now``), None while it is not."""
        if self.alive is False:
            return self.lost_at
        heard = max(t for t in (self.health_at, self.frame_at, self.alive_at, 0.0) if t is not None)
        return heard + LOST_AFTER_S if now - heard > LOST_AFTER_S else None

    def tared(self, sensor_id: int) -> bool:
        frame = self.latest.get(sensor_id)
        return frame is not None and "taring" not in frame.flags

    def _elsewhere(self, what: str) -> RemoteBoardError:
        return RemoteBoardError(f"board {self.name} is read by another host's service ({self.source}): "
                                f"{what} it there")

    def loaded(self, sensor_id: int | None = None) -> dict:
        raise self._elsewhere("tare")

    def tare(self, sensor_id: int | None = None, force: bool = False):
        raise self._elsewhere("tare")

    def set_calibration(self, info, upload: dict) -> dict:
        raise self._elsewhere("upload calibrations to")

    def calibration(self, sensor_id: int) -> dict | None:
        sensor = ((self.health_document or {}).get("sensors") or {}).get(str(sensor_id))
        if sensor is None or sensor.get("calibration") is None:
            return None
        return {**sensor["calibration"], "document": None, "note_gateway": "the document is on the board's service"}

    def sensor_stale(self, sensor_id: int, age: float | None, now: float) -> bool:
        """Whether the sensor is stale, its last frame ``age`` s old (None: none
        yet): the board lost, no frame for LOST_AFTER_S, or its service says so
        (as of its last health document)."""
        remote = ((self.health_document or {}).get("sensors") or {}).get(str(sensor_id), {})
        return self.lost(now) or age is None or age > LOST_AFTER_S or bool(remote.get("stale"))

    def health_part(self, now: float) -> dict:
        """This board's part of the gateway's /health: the remote service's
        own (as of its last health document), with what the gateway sees."""
        document = self.health_document or {}
        lost = self.lost(now)
        sensors = {}
        for sid, info in sorted(self.sensors.items()):
            remote = (document.get("sensors") or {}).get(str(sid), {})
            latest = self.latest.get(sid)
            age = None if latest is None else now - latest.t_host
            meter = self.rates.get(sid)
            stale = self.sensor_stale(sid, age, now)
            sensors[str(sid)] = {**remote, "board": self.name, "id": sid, "kind": info.kind,
                                 "rate_hz": 0.0 if stale or meter is None else round(meter.rate_hz, 1),
                                 "stale": stale, "last_frame_age_s": None if age is None else round(age, 3)}
        claims = self.publishers(now) if self.publishers is not None else {"publisher": None, "publishers": [],
                                                                            "problems": []}
        problems = claims["problems"] + list(document.get("problems") or [])
        part = {key: document.get(key) for key in BOARD_FIELDS}
        if lost:  # the remote service's last word on its link no longer holds
            why = "its service's liveliness token is gone" if self.alive is False else \
                f"nothing heard for {LOST_AFTER_S} s"
            problems.insert(0, f"lost: the service of board {self.name} ({why})")
            part["link"] = {**(part["link"] or {}), "source": self.source, "state": "down", "up": False,
                            "last_error": f"the service of board {self.name} is lost ({why})"}
        return {
            "source": self.source,
            "status": "degraded" if lost or problems else "ok",
            "problems": problems,
            "notes": list(document.get("notes") or []),
            **part,
            "sensors": sensors,
            "remote": {"lost": lost, "alive": self.alive, "publisher": claims["publisher"],
                       "publishers": claims["publishers"],
                       "lost_for_s": None if self.lost_at is None else round(now - self.lost_at, 3),
                       "last_health_age_s": None if self.health_at is None else round(now - self.health_at, 3),
                       "last_frame_age_s": None if self.frame_at is None else round(now - self.frame_at, 3)},
        }
