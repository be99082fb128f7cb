"""``snds app``: a local web page to draw demonstrations, train a stable policy on them, and
push it around (needs the ``app`` extra: ``pip install 'snds[app]'``).

:func:`create_app` is the server (a Starlette application: the JSON API and the page's static
files), :func:`serve` runs it on uvicorn; :mod:`snds.app.worker` trains in worker processes
and :mod:`snds.app.strokes` validates the strokes and writes them as the CSV ``snds train``
reads. The server's requests and answers are read and written by :mod:`snds.app.messages`,
what it computes from a job by :mod:`snds.app.results`, and :mod:`snds.app.hosts` refuses
other host names.
"""

from snds.app.server import create_app, serve
from snds.app.strokes import LIMITS, Limits
from snds.errors import RequestError

__all__ = ["LIMITS", "Limits", "RequestError", "create_app", "serve"]
