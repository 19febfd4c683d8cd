"""The Desk's token: what a browser must show before it gets anything from a Desk reachable by others.

Bound to an address other than loopback, the Desk makes a random token at start and
prints it in the page's URL (``http://HOST:PORT/?token=...``), as notebook servers
do. ``TokenGate`` is plain ASGI middleware in front of everything the server answers,
pages, NiceGUI's own scripts, the websocket and the run files alike: a request
carries the token in the query (``?token=``, then it is kept in a cookie) or in the
cookie; without it the answer is HTTP 401, with a wrong one 403, and a websocket is
refused before it opens.

Bound to loopback the Desk needs no token (only this computer reaches it), but a web
page from elsewhere could still reach it through its own name pointed at 127.0.0.1
(DNS rebinding). ``HostGate`` refuses with 403 every request and websocket whose
``Host`` header is not one of this computer's own names for the Desk (127.0.0.1,
localhost, [::1], the address it is bound to; with the Desk's port, or without one).
"""

import hmac
import secrets
from http.cookies import SimpleCookie
from urllib.parse import parse_qs

COOKIE = "motorjig_desk_token"  # + "_PORT": cookies go by host, not port, and two Desks may share a host


def new_token():
    return secrets.token_urlsafe(24)


def cookie_name(port):
    return "%s_%d" % (COOKIE, port)


def _given(scope, cookie_name):
    """(token from the query, token from the cookie); either may be None."""
    query = parse_qs(scope.get("query_string", b"").decode("latin-1")).get("token", [None])[0]
    cookie = None
    for name, value in scope.get("headers", ()):
        if name == b"cookie":
            jar = SimpleCookie()
            try:
                jar.load(value.decode("latin-1"))
            except Exception:  # a malformed cookie header is no token
                continue
            if cookie_name in jar:
                cookie = jar[cookie_name].value
    return query, cookie


class TokenGate:
    """ASGI middleware: every HTTP request and websocket needs the token (query or cookie)."""

    def __init__(self, app, token, port):
        self.app = app
        self.token = token
        self.cookie = cookie_name(port)

    def _ok(self, value):
        return value is not None and hmac.compare_digest(value.encode(), self.token.encode())

    async def __call__(self, scope, receive, send):
        if scope["type"] not in ("http", "websocket"):
            return await self.app(scope, receive, send)
        query, cookie = _given(scope, self.cookie)
        if self._ok(query) or self._ok(cookie):
            if self._ok(query) and not self._ok(cookie) and scope["type"] == "http":
                send = self._setting_cookie(send)
            return await self.app(scope, receive, send)
        status = 401 if query is None and cookie is None else 403
        text = ("MotorJig Desk: this page needs its token: open the URL the Desk printed at start "
                "(http://HOST:PORT/?token=...)\n" if status == 401 else
                "MotorJig Desk: wrong token: open the URL the Desk printed at start\n").encode()
        await _refuse(scope, send, status, text)
        return None

    def _setting_cookie(self, send):
        cookie = ("%s=%s; Path=/; HttpOnly; SameSite=Strict" % (self.cookie, self.token)).encode()

        async def wrapped(message):
            if message["type"] == "http.response.start":
                message = dict(message, headers=list(message.get("headers", [])) + [(b"set-cookie", cookie)])
            await send(message)
        return wrapped


LOOPBACK_HOSTS = ("127.0.0.1", "localhost", "[::1]")


def allowed_hosts(host, port):
    """The Host header values a loopback Desk bound to ``host`` on ``port`` answers (lowercase)."""
    names = set(LOOPBACK_HOSTS)
    if host:
        names.add("[%s]" % host if ":" in host and not host.startswith("[") else host)
    names = {n.lower() for n in names}
    return frozenset(names | {"%s:%d" % (n, port) for n in names})


def _host_header(scope):
    for name, value in scope.get("headers", ()):
        if name == b"host":
            return value.decode("latin-1").strip().lower()
    return None


class HostGate:
    """ASGI middleware for a loopback Desk: a request or websocket whose Host header is not one
    of this computer's own names for the Desk is refused with 403 (DNS rebinding)."""

    def __init__(self, app, host, port):
        self.app = app
        self.allowed = allowed_hosts(host, port)

    async def __call__(self, scope, receive, send):
        if scope["type"] not in ("http", "websocket") or _host_header(scope) in self.allowed:
            return await self.app(scope, receive, send)
        text = ("MotorJig Desk: refused: the page was asked for under another name (Host %r); open it as "
                "http://127.0.0.1:PORT/ or http://localhost:PORT/\n" % (_host_header(scope) or "")).encode()
        await _refuse(scope, send, 403, text)
        return None


async def _refuse(scope, send, status, text):
    """Answer ``status`` with ``text``: a plain HTTP response, or a websocket refused before it opens."""
    if scope["type"] == "websocket":
        if "websocket.http.response" in scope.get("extensions", {}):
            await send({"type": "websocket.http.response.start", "status": status,
                        "headers": [(b"content-type", b"text/plain; charset=utf-8")]})
            await send({"type": "websocket.http.response.body", "body": text})
        else:  # the server answers 403 to a websocket closed before it was accepted
            await send({"type": "websocket.close", "code": 1008})
        return
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"text/plain; charset=utf-8"),
                            (b"content-length", str(len(text)).encode()),
                            (b"cache-control", b"no-store")]})
    await send({"type": "http.response.body", "body": text})
