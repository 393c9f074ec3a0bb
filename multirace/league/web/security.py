"""What keeps the league's web app safe on a network: body-size caps, rate limits, CSRF tokens, headers.

- `BodyLimit`: an ASGI middleware that refuses a request body over the cap before it is stored (a
  Content-Length over the cap is refused before the app sees it; a chunked body is counted as it streams
  in). The rest of a refused body, up to `DRAIN_BYTES`, is read and dropped before the 413 goes out: a
  client that sends its whole body before it reads the answer (curl, Python's http.client) then gets the
  413 in plain words instead of a connection reset.
- `RateLimiter`: at most N events per key in a sliding window (uploads per entrant, failed tokens per client).
- CSRF: forms carry a random token that must equal the one in a SameSite=Strict cookie (double submit), and a
  cross-origin Origin header is refused. The JSON API takes the entrant's token in the Authorization header,
  which a cross-site form cannot send.
- `SecurityHeaders`: nosniff, referrers only to this site (so forms carry a real Origin), same-origin
  framing and a same-origin Content-Security-Policy.
"""
from __future__ import annotations

import collections
import hmac
import secrets
import threading
import time
from urllib.parse import urlsplit

DRAIN_BYTES = 64 << 20  # of a refused body, read and dropped before the 413 (beyond: the connection closes)
CSRF_COOKIE = "multirace_csrf"
CSRF_FIELD = "csrf_token"
PAGE_POLICY = ("default-src 'self'; img-src 'self' data:; media-src 'self'; frame-src 'self'; "
               "object-src 'none'; base-uri 'none'; form-action 'self'; frame-ancestors 'self'")
VIEWER_POLICY = ("default-src 'self'; script-src 'self' 'unsafe-inline' 'wasm-unsafe-eval'; "
                 "style-src 'self' 'unsafe-inline'; img-src 'self' data: blob:; worker-src 'self' blob:; "
                 "object-src 'none'; base-uri 'none'; frame-ancestors 'self'")


class BodyTooLarge(Exception):
    """A request body went over the cap while it streamed in."""


class BodyLimit:
    """ASGI middleware: request bodies of POSTs at most `limit` bytes; over it, 413 before reading on."""

    def __init__(self, app, limit: int):
        self.app, self.limit = app, limit

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http" or scope["method"] != "POST":
            return await self.app(scope, receive, send)
        length = dict(scope["headers"]).get(b"content-length")
        if length is not None and (not length.isdigit() or int(length) > self.limit):
            if length.isdigit() and int(length) <= DRAIN_BYTES:
                await _drain(receive)
            return await _too_large(send, self.limit)
        seen = 0
        started = False

        async def counted():
            nonlocal seen
            message = await receive()
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                if seen > self.limit:
                    raise BodyTooLarge()
            return message

        async def watched(message):
            nonlocal started
            started = started or message["type"] == "http.response.start"
            await send(message)

        try:
            await self.app(scope, counted, watched)
        except BodyTooLarge:
            if not started:
                await _drain(receive, DRAIN_BYTES - seen)
                await _too_large(send, self.limit)


async def _drain(receive, most: int = DRAIN_BYTES) -> None:
    """Read and drop the rest of the request body, up to about `most` bytes."""
    dropped = 0
    while dropped <= most:
        message = await receive()
        if message["type"] != "http.request" or not message.get("more_body", False):
            return
        dropped += len(message.get("body", b""))


async def _too_large(send, limit: int) -> None:
    body = (f'{{"error": "refused: the request is over {limit // 2**20} MB (the upload limit)"}}').encode()
    await send({"type": "http.response.start", "status": 413,
                "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
                            (b"connection", b"close")]})
    await send({"type": "http.response.body", "body": body})


class RateLimiter:
    """At most `count` events per key within `seconds` (a sliding window, in memory, thread-safe)."""

    def __init__(self, count: int, seconds: float):
        self.count, self.seconds = count, seconds
        self._events: dict = collections.defaultdict(collections.deque)
        self._lock = threading.Lock()

    def allow(self, key) -> bool:
        """Record an event for `key` and say whether it is within the limit (a refused one is not recorded)."""
        now = time.monotonic()
        with self._lock:
            events = self._events[key]
            while events and now - events[0] > self.seconds:
                events.popleft()
            if len(events) >= self.count:
                return False
            events.append(now)
            return True


def new_csrf_token() -> str:
    """A fresh random CSRF token for a form and its cookie."""
    return secrets.token_urlsafe(32)


def csrf_ok(request, form) -> bool:
    """True if the form's CSRF token equals the cookie's, and the request's Origin (if sent) is this host."""
    cookie, field = request.cookies.get(CSRF_COOKIE, ""), form.get(CSRF_FIELD, "")
    if not cookie or not isinstance(field, str) or not hmac.compare_digest(cookie.encode(), field.encode()):
        return False
    origin = request.headers.get("origin")
    return origin is None or urlsplit(origin).netloc == request.headers.get("host")


def bearer_token(request) -> str | None:
    """The token of an `Authorization: Bearer TOKEN` header, or None."""
    kind, _, token = request.headers.get("authorization", "").partition(" ")
    return token.strip() if kind.lower() == "bearer" and token.strip() else None


class SecurityHeaders:
    """ASGI middleware adding nosniff, a same-origin referrer policy, same-origin framing and a CSP."""

    def __init__(self, app):
        self.app = app

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        policy = VIEWER_POLICY if scope["path"].startswith("/viewer/") else PAGE_POLICY

        async def with_headers(message):
            if message["type"] == "http.response.start":
                message.setdefault("headers", [])
                message["headers"] = list(message["headers"]) + [
                    (b"x-content-type-options", b"nosniff"), (b"referrer-policy", b"same-origin"),
                    (b"x-frame-options", b"SAMEORIGIN"), (b"content-security-policy", policy.encode())]
            await send(message)

        await self.app(scope, receive, with_headers)
