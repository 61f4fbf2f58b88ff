"""``python -m mavest``: the ``mavest`` command, through its entry point."""

from mavest.launch import command

if __name__ == "__main__":  # (importing it, as a walk over the package does, runs nothing)
    command()
