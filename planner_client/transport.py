"""JSON over HTTP with timeouts, retries and errors that name the service and its URL.

Both services the planner talks to are plain JSON APIs behind the same failure modes: a process
that is starting (connection refused, 503 from ``/readyz``), one that died or is overloaded
(connection errors, 5xx), and a request that is wrong (4xx). Only the first two are worth
retrying, with exponential backoff; a 4xx would fail the same way again, so it is raised at once
with the service's ``{"error": {"field", "rule", "message"}}`` details. A service that sheds load
answers 503 with ``Retry-After``: the next try waits at least that long (capped by the policy's
``max_retry_after``), so an overloaded service is not hammered by the very clients it refused.

Every call carries the ``X-Request-ID`` of the work it belongs to (:func:`request_id`: the trial
loop sets one per trial and stores it in the trial's record), so both services' log lines of one
trial can be found by it.
"""

from __future__ import annotations

import random
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass
from typing import Any, Callable

import httpx

from firp.core.tracing import configure_tracing, instrument_client


REQUEST_ID_HEADER = "X-Request-ID"
TRACING_SERVICE_NAME = "firp-planner"  # the planner client's name in traces (OTEL_SERVICE_NAME overrides)
_REQUEST_ID: ContextVar[str | None] = ContextVar("firp_request_id", default=None)
_RANDOM = random.Random()  # the retries' jitter: not the simulation's or the planner's random streams


@contextmanager
def request_id(value: str | None = None) -> Iterator[str]:
    """Every call made inside carries ``X-Request-ID: value`` (default: a new random id)."""
    value = value or uuid.uuid4().hex
    token = _REQUEST_ID.set(value)
    try:
        yield value
    finally:
        _REQUEST_ID.reset(token)


def current_request_id() -> str | None:
    return _REQUEST_ID.get()


@dataclass(frozen=True)
class RetryPolicy:
    """``attempts`` tries in all; the wait before retry ``k`` (1-based) is ``base_delay * 2**(k-1)``,
    capped at ``max_delay``, or the server's ``Retry-After`` if longer; then stretched by a random
    share up to ``jitter`` (never shortened).

    Why the jitter: a service that sheds a burst refuses many clients within milliseconds, all with
    the same ``Retry-After``; without it they all come back in the same millisecond a second later,
    as a burst again (measured on the scoring service: 64 clients kept returning in waves)."""

    attempts: int = 4
    base_delay: float = 0.25
    max_delay: float = 4.0
    max_retry_after: float = 30.0  # the longest Retry-After honoured
    jitter: float = 0.5  # the wait is delay * (1 + U(0, jitter))

    def delay(self, retry: int, retry_after: float | None = None) -> float:
        """The least wait before retry ``retry``: the backoff, or the server's ``Retry-After`` if longer."""
        backoff = min(self.max_delay, self.base_delay * 2 ** (retry - 1))
        return backoff if retry_after is None else max(backoff, min(retry_after, self.max_retry_after))

    def wait(self, retry: int, retry_after: float | None = None, rng: random.Random = _RANDOM) -> float:
        """The wait before retry ``retry``: :meth:`delay` stretched by the jitter."""
        return self.delay(retry, retry_after) * (1.0 + self.jitter * rng.random())


def retry_after_seconds(response: httpx.Response) -> float | None:
    """``Retry-After`` in seconds (RFC 9110 delay-seconds; an HTTP date is not honoured), or None."""
    value = response.headers.get("retry-after")
    if value is None or not value.strip().isdigit():
        return None
    return float(value.strip())


class ServiceError(RuntimeError):
    """A call to ``service`` at ``url`` failed."""

    def __init__(self, service: str, url: str, message: str):
        super().__init__(message)
        self.service = service
        self.url = url


class ServiceUnavailable(ServiceError):
    """Unreachable, failing with 5xx, or not ready: after all retries. Restarting it may help."""


class RequestRejected(ServiceError):
    """A 4xx: the request is wrong; ``field`` and ``rule`` say how (when the service says)."""

    def __init__(self, service: str, url: str, status: int, field: str | None, rule: str | None, detail: str):
        where = f" (field {field!r}, rule {rule!r})" if field or rule else ""
        super().__init__(service, url, f"{service} at {url} rejected the request with HTTP {status}{where}: {detail}")
        self.status = status
        self.field = field
        self.rule = rule
        self.detail = detail


def _error_details(response: httpx.Response) -> tuple[str | None, str | None, str]:
    """field, rule, message from our error shape, FastAPI's default shape, or the raw text."""
    try:
        body = response.json()
    except ValueError:
        return None, None, response.text[:500] or response.reason_phrase
    if isinstance(body, dict) and isinstance(body.get("error"), dict):
        err = body["error"]
        return err.get("field"), err.get("rule"), str(err.get("message", err))
    if isinstance(body, dict) and "detail" in body:
        return None, None, str(body["detail"])[:500]
    return None, None, str(body)[:500]


class JsonHttp:
    """A retrying JSON client for one service (``name`` appears in every error message)."""

    def __init__(self, name: str, base_url: str, *, timeout: float = 60.0, connect_timeout: float = 3.0,
                 retry: RetryPolicy = RetryPolicy(), headers: dict[str, str] | None = None,
                 sleep: Callable[[float], None] = time.sleep):
        self.name = name
        self.base_url = base_url.rstrip("/")
        self.retry = retry
        self._sleep = sleep
        self._client = httpx.Client(base_url=self.base_url, headers=headers or {},
                                    timeout=httpx.Timeout(timeout, connect=connect_timeout))
        provider = configure_tracing(TRACING_SERVICE_NAME)
        if provider is not None:  # a span per call, and the trace context sent with it (traceparent)
            instrument_client(self._client, provider)

    def request(self, method: str, path: str, json: Any = None) -> httpx.Response:
        """The 2xx response; raises :class:`RequestRejected` on 4xx at once, :class:`ServiceUnavailable`
        when connection errors or 5xx persist through every attempt."""
        url = self.base_url + path
        last = ""
        retry_after: float | None = None
        for attempt in range(1, self.retry.attempts + 1):
            if attempt > 1:
                self._sleep(self.retry.wait(attempt - 1, retry_after))
            retry_after = None
            rid = _REQUEST_ID.get()
            try:
                response = self._client.request(method, path, json=json,
                                                headers={REQUEST_ID_HEADER: rid} if rid else None)
            except httpx.TransportError as exc:
                last = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
                continue
            if response.status_code >= 500:
                retry_after = retry_after_seconds(response) if response.status_code == 503 else None
                field, rule, detail = _error_details(response)
                last = f"HTTP {response.status_code}" + (f" ({rule})" if rule else "") + f": {detail}"
                continue
            if response.status_code >= 400:
                field, rule, detail = _error_details(response)
                raise RequestRejected(self.name, url, response.status_code, field, rule, detail)
            return response
        raise ServiceUnavailable(self.name, url, f"{self.name} at {self.base_url} is unreachable or failing: "
                                                 f"{method} {url} failed {self.retry.attempts} times; last: {last}")

    def wait_ready(self, timeout: float = 60.0, path: str = "/readyz", poll: float = 0.2) -> None:
        """Poll ``path`` until it answers 200 (503 and connection errors mean: not yet)."""
        url = self.base_url + path
        deadline = time.monotonic() + timeout
        last = "no answer yet"
        while True:
            try:
                response = self._client.get(path, timeout=min(5.0, max(0.5, timeout)))
                if response.status_code == 200:
                    return
                _, rule, detail = _error_details(response)
                last = f"HTTP {response.status_code}" + (f" ({rule})" if rule else "") + f": {detail}"
            except httpx.TransportError as exc:
                last = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
            if time.monotonic() + poll > deadline:
                raise ServiceUnavailable(self.name, url, f"{self.name} at {self.base_url} is not ready after "
                                                         f"{timeout:g} s (GET {url}); last: {last}")
            self._sleep(poll)

    def close(self) -> None:
        self._client.close()
