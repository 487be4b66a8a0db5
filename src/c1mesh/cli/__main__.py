"""`python -m c1mesh.cli`: the `c1mesh` command (named `python -m c1mesh.cli` in its usage lines)."""
from c1mesh.cli import main
from c1mesh.core.platform_memory import hold_freed_heap, prefer_small_pages, sleep_idle_blas

if __name__ == "__main__":  # pragma: no cover
    prefer_small_pages()            # as the c1mesh command does, before numpy is imported
    hold_freed_heap()
    sleep_idle_blas()
    main()
