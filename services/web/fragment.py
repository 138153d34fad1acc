"""The fragment page (``/fragments/<id>``) — owned by the archive-viewer engineer (issue 17).

Registered by :func:`services.web.create_app`; it has no routes yet.
"""

from __future__ import annotations

from flask import Blueprint

bp = Blueprint("fragment", __name__)
