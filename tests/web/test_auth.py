"""Tests of common/web/auth.py: the station's access token."""

import os
import stat

import pytest

from common.web.auth import bearer_token, load_or_create_token, session_secret, token_matches


def test_token_is_generated_once_private_and_kept(tmp_path):
    path = tmp_path / "state" / "web_token"
    first = load_or_create_token(path)
    assert len(first) >= 32
    assert stat.S_IMODE(os.stat(path).st_mode) == 0o600
    assert load_or_create_token(path) == first
    assert load_or_create_token(tmp_path / "other") != first


def test_truncated_token_file_is_refused(tmp_path):
    path = tmp_path / "web_token"
    path.write_text("abc\n")
    with pytest.raises(ValueError, match="shorter"):
        load_or_create_token(path)


def test_token_matches_only_the_exact_token():
    assert token_matches("s3cret-token-value", "s3cret-token-value")
    assert not token_matches("s3cret-token-valuE", "s3cret-token-value")
    assert not token_matches("s3cret-token-valu", "s3cret-token-value")
    assert not token_matches("", "s3cret-token-value")
    assert not token_matches(None, "s3cret-token-value")
    assert not token_matches("é", "s3cret-token-value")


def test_bearer_header_parsing():
    assert bearer_token("Bearer abc") == "abc"
    assert bearer_token("bearer   abc ") == "abc"
    assert bearer_token("Basic abc") is None
    assert bearer_token("Bearer ") is None
    assert bearer_token(None) is None


def test_session_secret_changes_with_the_token():
    assert session_secret("a" * 20) != session_secret("b" * 20)
    assert len(session_secret("a" * 20)) == 32


# -- issue 19: wrong Bearer tokens are slowed like the login form; absurd picture ids are 404 ----------

def _app(tmp_path, review=None):
    from services import web
    from tests.web.conftest import TOKEN
    return web.create_app(token=TOKEN, store_root=tmp_path, review=review), TOKEN


def test_wrong_bearer_tokens_are_slowed_and_the_right_one_is_not(tmp_path):
    import time

    from common.web.auth import FAILED_ATTEMPT_DELAY_S
    app, token = _app(tmp_path)
    c = app.test_client()
    t0 = time.perf_counter()
    for guess in ("a" * 43, "b" * 43, token[:-1]):
        r = c.post("/api/review/verdict", json={}, headers={"Authorization": f"Bearer {guess}"})
        assert r.status_code == 401
    wrong = time.perf_counter() - t0
    assert wrong >= 3 * FAILED_ATTEMPT_DELAY_S * 0.95, f"3 wrong guesses took {wrong:.2f} s: not slowed"
    t0 = time.perf_counter()
    r = c.post("/api/review/verdict", json={}, headers={"Authorization": f"Bearer {token}"})
    assert r.status_code != 401 and time.perf_counter() - t0 < FAILED_ATTEMPT_DELAY_S


class _SqliteReview:
    """Stands in for the review data: looks the proposal id up in SQLite as the real one does."""

    def picture(self, pid, view, max_side_px=640, pose=None):
        import sqlite3
        con = sqlite3.connect(":memory:")
        con.execute("SELECT ?", (pid,)).fetchone()  # OverflowError beyond 64 bits
        raise LookupError(f"no proposal {pid}")


def test_a_huge_picture_id_is_not_found_not_a_server_error(tmp_path):
    app, _ = _app(tmp_path, review=_SqliteReview())
    c = app.test_client()
    assert c.get("/api/review/picture/7/pair-colour.png").status_code == 404
    assert c.get(f"/api/review/picture/{2 ** 64 + 5}/pair-colour.png").status_code == 404
