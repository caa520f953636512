"""``python -m gtforge.cli``: the ``gtforge`` command."""
from gtforge.cli import main

main()
