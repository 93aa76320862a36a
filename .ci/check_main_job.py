"""Checks what the README's main job (`polydem run`, the default scene) left behind.

Reads the closing lines the run printed and its summary: the run finished (not interrupted), and
every file that the summary lists as an output exists and is not empty, among them a USD
animation, the summary itself and a PNG picture of the final frame.
"""

import json
import re
import sys
from pathlib import Path


def main(log_path: str) -> int:
    log = Path(log_path).read_text(errors="replace")
    m = re.search(r"written to (.+?)[/\\\\]?:", log)
    if m is None:
        print("CI: the main job's closing lines name no output folder ('written to ...')")
        return 1
    folder = Path(m.group(1).strip())
    summary_path = folder / "summary.json"
    if not summary_path.is_file():
        print(f"CI: no summary at {summary_path}")
        return 1
    summary = json.loads(summary_path.read_text())
    problems = []
    if summary.get("interrupted"):
        problems.append(f"the run was interrupted: {summary.get('reason')}")
    outputs = summary.get("outputs", {})
    files = []
    for key, value in outputs.items():
        if key in ("folder",) or value is None:
            continue
        for name in value if isinstance(value, list) else [value]:
            if isinstance(name, str):
                files.append(name)
    for name in files:
        path = folder / name
        if not path.exists() or (path.is_file() and path.stat().st_size == 0):
            problems.append(f"listed output {name} is missing or empty")
        elif name not in log:
            problems.append(f"output {name} is not named in the closing lines")
    if not any(name.endswith(".png") for name in files):
        problems.append("no PNG picture of the final frame")
    if not any(name.endswith((".usd", ".usdc", ".usda")) for name in files):
        problems.append("no USD animation")
    for p in problems:
        print(f"CI: {p}")
    if not problems:
        print(f"CI: the main job wrote {len(files)} files in {folder}: {', '.join(files)}")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1]))
