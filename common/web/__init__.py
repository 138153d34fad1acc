"""Helpers of the station's web pages (served by the package ``services/web/``).

* :mod:`common.web.auth`     — access token, constant-time checks, session/CSRF values
* :mod:`common.web.bench`    — :class:`BenchSession`: the operator hand-shake around the capture
* :mod:`common.web.compose`  — pictures: pre-scan outline, fragments joined at a proposed pose
* :mod:`common.web.pipeline` — how far each fragment got, read from the storage tree
* :mod:`common.web.review`   — proposals, verdict history and pictures for the review page
"""
