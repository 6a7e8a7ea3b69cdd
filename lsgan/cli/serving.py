"""``lsgan serve``: the HTTP server and its page."""
from __future__ import annotations

import os

import click

from lsgan.cli.group import main
from lsgan.cli.options import In, fail
from lsgan.errors import describe


@main.command(epilog="""\b
Examples:
  lsgan serve --gan runs/gan --vae runs/vae                 # http://127.0.0.1:8000/ : the page; the API at /v1
  lsgan serve --model gan-onnx                              # an `export-model --onnx` folder (onnxruntime)
  lsgan serve --model gan-onnx --int8 --port 8080
  LSGAN_API_KEY=secret lsgan serve --gan runs/gan --vae runs/vae --host 0.0.0.0   # reachable from other machines
  lsgan serve --gan runs/gan --vae runs/vae --api-key-file key.txt --allow-host motion.example.org
  lsgan serve --gan runs/gan --vae runs/vae --max-num 4 --max-in-flight 32 --timeout 5
  lsgan serve --gan runs/gan --vae runs/vae --workers 1     # one engine process (least memory)
  curl -s localhost:8000/v1/generate -H 'Content-Type: application/json' -d '{"text": "a person waves", "seed": 1}'
\b
The API (endpoints, limits, errors): docs/api.md, and /docs on the running server. SIGTERM finishes the requests
in flight and exits 0 (Ctrl-C: 130); a second signal does not cut that short.
""")
@click.option("--gan", type=In(exists=True), help="GAN checkpoint (run or checkpoint folder); with --vae.")
@click.option("--vae", type=In(exists=True), help="The VAE whose latents the GAN learned.")
@click.option("--model", type=In(exists=True, file_okay=False),
              help="Instead of --gan/--vae: a folder `lsgan export-model --onnx` wrote (runs without torch's models).")
@click.option("--int8", is_flag=True, help="--model: the int8 decoder (an export made with --int8).")
@click.option("--host", default="127.0.0.1", show_default=True,
              help="Address to listen on; anything but loopback makes the server reachable from other machines.")
@click.option("--port", default=8000, show_default=True, type=click.IntRange(0, 65535), help="TCP port (0: any free one).")
@click.option("--api-key", envvar="LSGAN_API_KEY", show_envvar=True,
              help="Require this key on /v1 (Authorization: Bearer KEY or X-API-Key); the page and /healthz stay open. "
                   "Visible ASCII only. On the command line it shows in the process list: prefer LSGAN_API_KEY or "
                   "--api-key-file.")
@click.option("--api-key-file", type=In(exists=True, dir_okay=False),
              help="Read the API key from this file's first line (instead of --api-key).")
@click.option("--allow-host", "allow_hosts", multiple=True, metavar="NAME",
              help="Also answer requests whose Host header names NAME (repeatable; '*': any). By default only the "
                   "bound address's names are served (127.0.0.1, localhost, [::1] on loopback), against DNS rebinding.")
@click.option("--device", default="auto", show_default=True, help="--gan/--vae: auto, cpu, cuda or cuda:N.")
@click.option("--text-encoder-path", type=In(exists=True), help="Local weights of the GAN's text encoder.")
@click.option("--text-cache", default=1024, show_default=True, type=click.IntRange(0),
              help="Prompt embeddings kept across requests (0: none).")
@click.option("--workers", type=click.IntRange(1),
              help="Engine processes, each with its own copy of the models, whose passes run side by side under "
                   "load (default: one per core, at most 4; one on a GPU).")
@click.option("--max-text-chars", default=500, show_default=True, type=click.IntRange(1), help="Longest prompt.")
@click.option("--min-frames", default=4, show_default=True, type=click.IntRange(1), help="Shortest motion.")
@click.option("--max-frames", type=click.IntRange(1),
              help="Longest motion (default: the model's maximum, at most 196; never more than the model's).")
@click.option("--default-frames", type=click.IntRange(1), help="Length when a request gives none (default 120).")
@click.option("--max-num", default=8, show_default=True, type=click.IntRange(1), help="Motions per request.")
@click.option("--max-control-num", default=2, show_default=True, type=click.IntRange(1),
              help="Motions per request with constraints (each optimised for tenths of a second on a CPU).")
@click.option("--max-body-bytes", default=16384, show_default=True, type=click.IntRange(64), help="Largest request body.")
@click.option("--max-in-flight", default=64, show_default=True, type=click.IntRange(1),
              help="Requests admitted at once; more get 503 with Retry-After.")
@click.option("--timeout", "timeout_s", default=10.0, show_default=True, type=click.FloatRange(min=0, min_open=True),
              help="Seconds a request may take; then 503.")
@click.option("--gather-ms", default=1.0, show_default=True, type=click.FloatRange(0, 1000),
              help="How long a pass waits for more requests to batch with the first.")
@click.option("--max-batch", default=8, show_default=True, type=click.IntRange(1),
              help="Motions in one engine pass (smaller passes let answers go out while the next pass runs).")
@click.option("--store-size", default=256, show_default=True, type=click.IntRange(1),
              help="Motions kept for download (least recently used dropped first).")
@click.option("--max-line-bytes", default=8192, show_default=True, type=click.IntRange(64),
              help="Longest request target (path and query); longer gets 414.")
@click.option("--max-header-bytes", default=65536, show_default=True, type=click.IntRange(1024),
              help="Largest request head (request line and headers); larger gets 431.")
@click.option("--max-headers", default=100, show_default=True, type=click.IntRange(8),
              help="Most header lines in a request; more gets 431.")
@click.option("--header-timeout", "header_timeout_s", default=10.0, show_default=True,
              type=click.FloatRange(min=0, min_open=True), help="Seconds for a request's head to arrive (the first from the connection's opening); then 408.")
@click.option("--body-timeout", "body_timeout_s", default=10.0, show_default=True,
              type=click.FloatRange(min=0, min_open=True), help="Seconds for a request's body to arrive; then 408.")
@click.option("--keep-alive", "keep_alive_s", default=5.0, show_default=True,
              type=click.FloatRange(min=0, min_open=True), help="Seconds an idle keep-alive connection stays open.")
@click.option("--max-connections", default=1024, show_default=True, type=click.IntRange(1),
              help="Open connections at once; past it the one waiting longest on its client is closed (503 when "
                   "every one is being answered).")
def serve(gan, vae, model, int8, host, port, api_key, api_key_file, allow_hosts, device, text_encoder_path,
          text_cache, workers, **limits) -> None:
    """Serve the model over HTTP: the API (/v1/generate, /v1/motions/ID.glb|.bvh|.npy, /v1/info), its OpenAPI
    docs (/docs) and a page at / to type a sentence, watch the motion and download it. Models load once;
    concurrent requests are batched into one generator and decoder pass."""
    from lsgan.models.text import TextEncoderUnavailable
    from lsgan.serve.limits import Limits
    from lsgan.serve.server import serve as run

    if model is not None and (gan is not None or vae is not None):
        raise click.UsageError("give --model (an exported folder) or --gan and --vae (checkpoints), not both")
    if model is None and (gan is None or vae is None):
        raise click.UsageError("give --gan RUN and --vae RUN, or --model EXPORT_DIR")
    if int8 and model is None:
        raise click.UsageError("--int8 goes with --model (an ONNX export made with --int8)")
    if model is not None and (text_encoder_path is not None or device not in ("auto", "cpu")):
        raise click.UsageError("--text-encoder-path and --device go with --gan/--vae (an export runs on the CPU)")
    if api_key_file is not None and api_key is not None:
        raise click.UsageError("give the key once: --api-key (or LSGAN_API_KEY) or --api-key-file")
    if api_key is None and os.environ.get("LSGAN_API_KEY") == "":
        fail("LSGAN_API_KEY is set but empty: give the key, or unset it to serve without one")
    try:
        from lsgan.serve.server import read_key_file

        key = read_key_file(api_key_file) if api_key_file is not None else api_key
        run(gan=gan, vae=vae, model=model, int8=int8, host=host, port=port, api_key=key, limits=Limits(**limits),
            device=device, text_encoder_path=text_encoder_path, text_cache=text_cache, workers=workers,
            allow_hosts=tuple(allow_hosts))
    except (ValueError, OSError, RuntimeError, TextEncoderUnavailable) as e:
        fail(describe(e))
