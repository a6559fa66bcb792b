"""The planner as an edge server: ``sb3-graph serve`` (:mod:`envs.serve.app`), the scene on the wire
(:mod:`envs.serve.wire`, :mod:`envs.serve.schema`) and a Python client (:mod:`envs.serve.client`).

See docs/serve.md. The server needs the ``serve`` extra (FastAPI, uvicorn); the client needs only
the standard library and numpy.
"""
