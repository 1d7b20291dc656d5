"""A world worker's episodes: a bounded, expiring in-memory store.

Clients start an episode and then execute plans on it, possibly many times; a client that goes
away must not make the worker grow without bound, so episodes expire after a TTL and, beyond a
maximum count, the oldest is evicted. An expired or evicted episode is not lost for good: it is
fully determined by (task, seed, pose error), so a client can simply start it again.
"""

from __future__ import annotations

import threading
import time
import uuid
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Callable

from world_api.backend import EpisodeStart


@dataclass(frozen=True)
class StoredEpisode:
    episode_id: str
    start: EpisodeStart = field(repr=False)
    pose_error: tuple[float, float]  # (mm, deg) as requested, reported back as given
    image_b64: str = field(repr=False)
    created_at: float  # seconds since the epoch
    expires_at: float


class EpisodeStore:
    """Insertion-ordered (= creation-ordered) episodes, at most ``max_count``, each living ``ttl`` s."""

    def __init__(self, max_count: int, ttl_seconds: float, clock: Callable[[], float] = time.time):
        if max_count < 1 or ttl_seconds <= 0:
            raise ValueError("max_count must be >= 1 and ttl_seconds > 0")
        self.max_count = max_count
        self.ttl_seconds = ttl_seconds
        self._clock = clock
        self._episodes: OrderedDict[str, StoredEpisode] = OrderedDict()
        self._lock = threading.Lock()

    def add(self, start: EpisodeStart, pose_error: tuple[float, float], image_b64: str) -> StoredEpisode:
        now = self._clock()
        episode = StoredEpisode(uuid.uuid4().hex, start, pose_error, image_b64, now, now + self.ttl_seconds)
        with self._lock:
            self._purge_expired(now)
            while len(self._episodes) >= self.max_count:
                self._episodes.popitem(last=False)
            self._episodes[episode.episode_id] = episode
        return episode

    def get(self, episode_id: str) -> StoredEpisode | None:
        with self._lock:
            self._purge_expired(self._clock())
            return self._episodes.get(episode_id)

    def delete(self, episode_id: str) -> bool:
        with self._lock:
            self._purge_expired(self._clock())
            return self._episodes.pop(episode_id, None) is not None

    def __len__(self) -> int:
        with self._lock:
            self._purge_expired(self._clock())
            return len(self._episodes)

    def _purge_expired(self, now: float) -> None:
        # every episode lives equally long, so creation order is expiry order: stop at the first live one
        while self._episodes:
            oldest = next(iter(self._episodes.values()))
            if oldest.expires_at > now:
                break
            self._episodes.popitem(last=False)
