"""The bench's outbox across versions: an entry a stricter schema now refuses never stops the
bench (docs/messages.md: a breaking change bumps v; this one tightened verdicts and annotations)."""

from __future__ import annotations

from common.bus.outbox import Outbox
from common.messages import new_message, pack
from common.store import Store


class _Accepting:
    def __init__(self):
        self.sent = []

    def submit(self, event):
        self.sent.append(event["uid"])
        return len(self.sent)


def test_an_entry_the_schema_now_refuses_is_listed_then_set_aside_and_the_rest_is_sent(tmp_path):
    box = Outbox(tmp_path / "bench")
    first = new_message("match.verified", fragment="A", other="B", verdict="confirmed")
    box.put(first)
    old = dict(new_message("match.verified", fragment="A", other="C", verdict="confirmed"), verdict="maybe")
    with box._lock:   # as an older, laxer version wrote it
        box._con.execute("INSERT INTO outbox (body) VALUES (?)", (pack(old),))
    last = new_message("fragment.annotated", fragment="A", by="x", changes={"notes": "n"})
    box.put(last)
    listed = box.pending()
    assert [e.get("uid") for _, e, _ in listed] == [first["uid"], old["uid"], last["uid"]]
    client = _Accepting()
    assert box.drain(client, Store(tmp_path / "storage")) == 3 and len(box) == 0
    assert client.sent == [first["uid"], last["uid"]]
    (_, kept, reason), = box.refused()
    assert kept["uid"] == old["uid"] and "not a valid message" in reason and "verdict" in reason
    box.close()
