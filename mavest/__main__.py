"""``python -m mavest``: the ``mavest`` command, through its entry point."""

from mavest.launch import main

if __name__ == "__main__":  # (importing it, as a walk over the package does, runs nothing)
    raise SystemExit(main())
