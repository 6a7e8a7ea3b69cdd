"""``python -m lsgan.cli``: the lsgan program."""
from lsgan.cli import main

main(prog_name="lsgan")  # its help and messages say `lsgan`, as the installed script does
