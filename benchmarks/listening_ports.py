"""TCP ports a command opens while it runs: every listening socket that was not there before,
sampled with ``ss -ltn`` every ``--every`` seconds, split into loopback and other addresses.

    python benchmarks/listening_ports.py [--every 0.2] -- COMMAND...

e.g. ``python benchmarks/listening_ports.py -- magail-sumo evaluate --policy random --city
data/sumo/cologne8/cologne8.sumocfg --city-steps 200 --out /tmp/city``. Prints the command's
exit code, the number of samples, and each new listener (address:port) with the samples that
saw it; exits 1 when any new listener was on a non-loopback address (the issue-31 check: the
tool's SUMO, libsumo and Ray listen on loopback only, or not at all).
"""

from __future__ import annotations

import argparse
import ipaddress
import subprocess
import sys
import time
from collections import Counter


def listeners() -> set[str]:
    """``address:port`` of every listening TCP socket of the machine (``ss -ltnH``)."""
    out = subprocess.run(["ss", "-ltnH"], capture_output=True, text=True, check=True).stdout
    return {line.split()[3] for line in out.splitlines() if line.strip()}


def is_loopback(addr: str) -> bool:
    host = addr.rsplit(":", 1)[0].strip("[]").split("%")[0]
    try:
        ip = ipaddress.ip_address(host)
    except ValueError:  # '*' (every address) and names
        return False
    mapped = getattr(ip, "ipv4_mapped", None)  # [::ffff:127.0.0.1]: IPv4 loopback over IPv6
    return ip.is_loopback or (mapped is not None and mapped.is_loopback)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--every", type=float, default=0.2, help="sampling period (s)")
    ap.add_argument("command", nargs=argparse.REMAINDER, help="-- COMMAND...")
    args = ap.parse_args(argv)
    cmd = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not cmd:
        ap.error("give the command after --")
    before = listeners()
    seen: Counter[str] = Counter()
    samples = 0
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    while proc.poll() is None:
        seen.update(listeners() - before)
        samples += 1
        time.sleep(args.every)
    err = proc.stderr.read() if proc.stderr else ""
    print(f"command exit code {proc.returncode}; {samples} samples of ss -ltn")
    if proc.returncode:
        print("stderr tail:", " ".join(err.split())[-400:])
    outside = {a: n for a, n in seen.items() if not is_loopback(a)}
    for addr, n in sorted(seen.items()):
        print(f"  new listener {addr} ({'loopback' if is_loopback(addr) else 'NOT loopback'}):"
              f" seen in {n} samples")
    print(f"new listeners: {len(seen)}, on non-loopback addresses: {len(outside)}")
    return 1 if outside else 0


if __name__ == "__main__":
    sys.exit(main())
