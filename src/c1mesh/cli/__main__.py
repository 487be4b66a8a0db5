"""`python -m c1mesh.cli`: the `c1mesh` command (named `python -m c1mesh.cli` in its usage lines)."""
from c1mesh.cli import main

if __name__ == "__main__":  # pragma: no cover
    main()
