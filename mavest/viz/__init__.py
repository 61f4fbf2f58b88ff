"""Visualisation: Rerun recordings, the default layout, and live viewers.

The Rerun SDK's own log lines (its Rust core writes them to stderr) are off
unless ``RUST_LOG`` says otherwise: mavest reports a viewer's failures itself,
once, in a sentence.
"""

import os

os.environ.setdefault("RUST_LOG", "off")
