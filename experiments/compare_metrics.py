"""Bit-identity check: every metric of every seed and generation of two `mqd sweep` folders.

    python experiments/compare_metrics.py BEFORE AFTER

BEFORE and AFTER are sweep folders, or digest files (`--digest FOLDER FILE`
writes one: per batch and metric, the SHA-256 of the values as float64, NaN
canonical; docs/data/ keeps digests of earlier versions). For each batch
(<task>_<algorithm>.json): the metrics both have, compared exactly (NaN equal
to NaN); metrics only one side has are listed. Exits 1 if a shared metric
differs.
"""

from __future__ import annotations

import hashlib
import json
import os
import sys

import numpy as np

from mqd_jax.experiment import results


def _digest(values: list) -> str:
    x = np.array(values, dtype=np.float64)
    x[np.isnan(x)] = np.nan  # one NaN bit pattern
    return hashlib.sha256(str(x.shape).encode() + x.tobytes()).hexdigest()


def digests(source: str) -> dict[str, dict[str, str]]:
    """{batch file: {metric: digest}} of a sweep folder, or as saved in a digest file."""
    if os.path.isfile(source):
        with open(source) as f:
            return json.load(f)
    batches, damaged = results.scan(source)  # every file's checksum verified
    if damaged:
        raise SystemExit(str(next(iter(damaged.values()))))
    return {os.path.basename(stem) + ".json": {m: _digest(v) for m, v in saved["metrics"].items()}
            for stem, saved in batches}


def compare(before: str, after: str) -> bool:
    same = True
    after_digests = digests(after)
    for name, a in digests(before).items():
        if name not in after_digests:
            print(f"{name}: missing in {after}")
            same = False
            continue
        b = after_digests[name]
        differs = False
        for metric in sorted(set(a) | set(b)):
            if metric not in b or metric not in a:
                print(f"{name} {metric}: only {'before' if metric in a else 'after'}")
                continue
            if a[metric] != b[metric]:
                print(f"{name} {metric}: DIFFERS")
                differs = True
        shared = len(set(a) & set(b))
        print(f"{name}: {'DIFFERS' if differs else 'bit-identical'} on the {shared} metrics both have")
        same &= not differs
    return same


if __name__ == "__main__":
    if sys.argv[1] == "--digest":
        os.makedirs(os.path.dirname(sys.argv[3]) or ".", exist_ok=True)
        with open(sys.argv[3], "w") as f:
            json.dump(digests(sys.argv[2]), f, indent=1)
    else:
        sys.exit(0 if compare(sys.argv[1], sys.argv[2]) else 1)
