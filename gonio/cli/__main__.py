"""`python -m gonio.cli`."""

from gonio.cli import main

main()
