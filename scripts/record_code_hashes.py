"""Add the per-file code hashes (``provenance.code_hashes``) to results files made before the
runner recorded them.

For every results file given (and every part of a merged file) the package is read from the
commit recorded in its provenance (``git archive``), its source hash is recomputed and must equal
the recorded ``package_hash``; only then are the code hashes of that same source
(:func:`pgm_wm.experiments.results.package_code_hashes`) written into the provenance, with a
``code_hashes_from`` line saying how they were obtained. Nothing else in the file changes.

    python scripts/record_code_hashes.py results/ch4_memory_arm.json results/ch5_hidden_payload_arm.json
"""

from __future__ import annotations

import io
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

from pgm_wm.experiments.results import load_results, package_code_hashes, package_source_hash, save_results

REPO = Path(__file__).resolve().parents[1]


def hashes_at(commit: str, expected_source_hash: str) -> dict[str, str]:
    archive = subprocess.run(["git", "archive", commit, "pgm_wm"], cwd=REPO, capture_output=True, check=True).stdout
    with tempfile.TemporaryDirectory() as tmp:
        with tarfile.open(fileobj=io.BytesIO(archive)) as tar:
            tar.extractall(tmp, filter="data")
        pkg = Path(tmp) / "pgm_wm"
        found = package_source_hash(pkg)
        if found != expected_source_hash:
            raise SystemExit(f"commit {commit[:10]}: its package source hash {found[:12]} is not the recorded "
                             f"{expected_source_hash[:12]}; refusing to record code hashes")
        return package_code_hashes(pkg)


def record(prov: dict) -> None:
    if prov.get("dirty"):
        raise SystemExit(f"commit {prov['commit'][:10]}: the run had uncommitted changes; cannot reconstruct its code")
    prov["code_hashes"] = hashes_at(prov["commit"], prov["package_hash"])
    prov["code_hashes_from"] = ("added after the run by scripts/record_code_hashes.py from pgm_wm/ at the recorded "
                                "commit, whose source hash equals package_hash")


def main(paths: list[str]) -> int:
    for path in paths:
        res = load_results(path)
        prov = res["provenance"]
        for part in prov.get("parts", []):
            record(part)
        record(prov)
        save_results(path, res)
        print(f"{path}: code hashes of {len(prov['code_hashes'])} files from commit {prov['commit'][:10]}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
