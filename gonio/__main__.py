"""``python -m gonio`` runs the command line."""

from gonio.cli import main

# Guarded: dask's local cluster starts its workers with multiprocessing's "spawn", which
# imports the parent's __main__ module in every worker (as __mp_main__).
if __name__ == "__main__":
    main()
