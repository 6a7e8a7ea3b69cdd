"""``python -m lsgan.cli``: the lsgan program."""
from lsgan.cli import main

main()
