"""``python -m mi_tetvr.cli``: the ``mi-tetvr`` command."""
from mi_tetvr.cli import main

main()
