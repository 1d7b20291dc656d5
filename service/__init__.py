"""The FIRP scoring service: a FastAPI app that loads an ensemble bundle and scores plans over HTTP.

Start it with ``python -m service --bundle DIR`` (see :mod:`service.__main__`), or build the app
with :func:`service.app.create_app` to embed or test it. Never imports mujoco: it needs only the
plan contract and the model (``firp``). Nothing is imported here, so that ``python -m service``
can check its flags before torch loads.
"""
