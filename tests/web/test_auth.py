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
