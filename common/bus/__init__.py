"""The station's message bus: broker, journal, worker runtime, client, event feed, outbox.

* :mod:`common.bus.broker`   — :class:`Broker` (Majordomo queues, routing, journal, event feed)
* :mod:`common.bus.journal`  — the broker's SQLite journal with group commit
* :mod:`common.bus.worker`   — :func:`run_worker` and :class:`StageContext`
* :mod:`common.bus.client`   — :class:`BrokerClient`: submit, status, rerun, since
* :mod:`common.bus.feed`     — :class:`FeedSubscriber`: ordered, gap-free event stream
* :mod:`common.bus.outbox`   — :class:`Outbox`: the bench's spool and durable outbox
* :mod:`common.bus.protocol` — frame constants (documented in ``docs/messages.md``)
"""
