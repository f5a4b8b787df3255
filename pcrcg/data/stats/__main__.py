"""``python -m pcrcg.data.stats``: see :mod:`pcrcg.data.stats.cli`."""

from pcrcg.data.stats.cli import main

if __name__ == "__main__":
    main()
