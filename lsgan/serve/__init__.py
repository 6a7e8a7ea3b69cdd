"""``lsgan serve``: the HTTP API and page over a loaded model (see docs/api.md).

``engine`` (models loaded once), ``batcher`` (micro-batching), ``store`` (motions kept for download), ``limits``,
``checks`` (a request body to an engine item), ``files`` (exports and the page's files), ``app`` (the FastAPI
app), ``server`` (uvicorn).
"""
