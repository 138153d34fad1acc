"""Log in / log out, and the access checks every write goes through (:func:`writes`).

Reading is open to whoever can reach the port. A write needs the station's access token: a
script sends ``Authorization: Bearer <token>`` (and the name to record in ``X-Tessera-Who``, :func:`who`);
a browser logs in once (``/login``, token + name), then carries a session cookie signed with a key
derived from the token and echoes the session's CSRF value in the ``X-CSRF-Token`` header. Writes also refuse other origins and non-JSON bodies.
"""

from __future__ import annotations

import functools
import time
from typing import Callable
from urllib.parse import urlsplit

from flask import Blueprint, abort, jsonify, redirect, render_template, request, session, url_for

from common.web import auth

from .station import station

bp = Blueprint("auth", __name__)


def logged_in() -> bool:
    """A browser logged in (the cookie is signed with a key derived from the token)."""
    return bool(session.get("auth"))


#: the header a script names its person or program in, as the login form's name (``Authorization: Bearer``)
WHO_HEADER = "X-Tessera-Who"


def who() -> str:
    """The name a write is recorded under (``by`` of a verdict or an edit), at most 64 characters.

    The token is the station's one shared secret and names nobody, so the name is the one its holder
    gave: a script sending ``Authorization: Bearer`` gives it in the :data:`WHO_HEADER` header, a browser
    at login. Without one: ``[services.web] operator``, else ``web``. Like the login's, the name is
    what the token holder says, not checked.
    """
    if auth.bearer_token(request.headers.get("Authorization")) is not None:
        given = request.headers.get(WHO_HEADER, "")
        try:   # a header arrives as ISO-8859-1 text; a name sent in UTF-8 (curl, most clients) is read as such
            given = given.encode("latin-1").decode("utf-8")
        except UnicodeError:
            pass
    else:
        given = session.get("who") or ""
    return (given.strip()[:64] or station().settings["operator"] or "web")[:64]


def authorised() -> bool:
    """A write is allowed with the bearer token, or a logged-in session echoing its CSRF value."""
    bearer = auth.bearer_token(request.headers.get("Authorization"))
    if bearer is not None:
        return auth.check_token_slowly(bearer, station().token)  # a wrong Bearer token is slowed like /login
    if not logged_in():
        return False
    return auth.token_matches(request.headers.get("X-CSRF-Token"), session.get("csrf", ""))


def same_origin() -> bool:
    """No ``Origin`` (a script, which still needs the token), this server's own address, or the address the
    pages are published under behind a TLS reverse proxy (``[services.web] public_origin``: the proxy speaks
    plain HTTP to this server, so the browser's ``https://…`` origin is not ``request.host_url``)."""
    origin = request.headers.get("Origin")
    if origin is None:
        return True
    public = station().settings["public_origin"]
    return origin == request.host_url.rstrip("/") or (bool(public) and origin == public)   # checked: no path


def writes(view: Callable) -> Callable:
    """Decorator of every write endpoint: same origin, the token (or session + CSRF), a JSON body."""
    @functools.wraps(view)
    def guarded(*args, **kwargs):
        if not same_origin():
            return jsonify(error="cross-site request refused"), 403
        if not authorised():
            return jsonify(error="log in with the station's access token to do this"), 401
        if not request.is_json:
            return jsonify(error="send the request body as application/json"), 415
        return view(*args, **kwargs)
    return guarded


def body() -> dict:
    """The request's JSON object (400 otherwise)."""
    data = request.get_json(silent=True)
    if not isinstance(data, dict):
        abort(400, "request body must be a JSON object")
    return data


@bp.get("/login")
def login_form():
    return render_template("login.html", page="login", error="", next=_safe_next(request.args.get("next")))


@bp.post("/login")
def login():
    nxt = _safe_next(request.form.get("next"))
    if not same_origin():
        abort(403)
    if not auth.token_matches(request.form.get("token", "").strip(), station().token):
        time.sleep(0.5)  # slows guessing; the token's 256 bits do the real work
        return render_template("login.html", page="login", error="That is not this station's access token.",
                               next=nxt), 401
    session.clear()
    session.permanent = True
    session.update(auth=True, csrf=auth.new_csrf_value(), who=request.form.get("who", "").strip()[:64])
    return redirect(nxt)


@bp.post("/logout")
def logout():
    if same_origin():
        session.clear()
    return redirect(url_for("index"))


def _safe_next(target: str | None) -> str:
    """Only local paths are followed after login (no open redirect), else the start page.

    Browsers drop tabs and newlines from a URL and read ``\\`` as ``/``, so ``/\\t/evil.example`` or
    ``/\\evil.example`` would lead to another site: control characters, spaces and backslashes are refused.
    """
    if (not target or not target.startswith("/") or target.startswith("//") or "\\" in target
            or any(c <= " " or c == "\x7f" for c in target)):
        return "/"
    parts = urlsplit(target)
    return "/" if parts.scheme or parts.netloc else target
