"""``python -m gtforge``: the ``gtforge`` command (as ``python -m gtforge.cli``)."""
from gtforge.cli import main

main()
