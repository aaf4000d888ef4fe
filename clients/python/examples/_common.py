"""What every example shares: the connection arguments."""

from __future__ import annotations

import argparse
import os
import sys
from typing import List, Optional, Tuple

# Run from a checkout without installing: the package sits next to examples/.
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from rigd_client import Client  # noqa: E402


def add_connection_args(p: argparse.ArgumentParser) -> None:
    """--url, --token, --data (the token falls back to $RIGD_TOKEN, $RIGD_DATA)."""
    p.add_argument("--url", default=os.environ.get("RIGD_URL", "http://127.0.0.1:8080"), help="the daemon (default: $RIGD_URL or %(default)s)")
    p.add_argument("--token", help="API token (default: $RIGD_TOKEN, else DATA/token)")
    p.add_argument("--data", help="the daemon's data directory, for its token file (default: $RIGD_DATA)")


def connect(args: argparse.Namespace, timeout: float = 60.0) -> Client:
    """A client from the parsed connection arguments."""
    return Client(args.url, token=args.token, data_dir=args.data, timeout=timeout)


def parse_directions(text: str) -> List[Tuple[float, float]]:
    """``"0,0;45,90"`` → ``[(0, 0), (45, 90)]`` (θ,φ in degrees)."""
    out = []
    for part in text.split(";"):
        if part.strip():
            theta, phi = (float(x) for x in part.split(","))
            out.append((theta, phi))
    if not out:
        raise argparse.ArgumentTypeError("no directions")
    return out


def parse_size(text: Optional[str]) -> Optional[Tuple[int, int]]:
    """``"64x48"`` → ``(64, 48)``."""
    if not text:
        return None
    w, h = text.lower().split("x")
    return int(w), int(h)
