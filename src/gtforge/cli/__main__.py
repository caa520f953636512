"""``python -m gtforge.cli``: the ``gtforge`` command."""
from gtforge.precompile import main

main()
