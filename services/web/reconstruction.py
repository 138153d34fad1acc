"""The reconstruction page (``/reconstruction``) — owned by the archive-recon engineer (issue 17).

Registered by :func:`services.web.create_app`; it has no routes yet.
"""

from __future__ import annotations

from flask import Blueprint

bp = Blueprint("reconstruction", __name__)
