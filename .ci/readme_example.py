"""Print the Python code block under a README heading (CI runs it in a bare install).

Usage: python .ci/readme_example.py README.md "Use the A layer in your own model"
Exits 3, printing why on stderr, when the heading or its code block is absent (CI then fails).
"""

import re
import sys
from pathlib import Path

readme, heading = Path(sys.argv[1]).read_text(), sys.argv[2]
match = re.search(rf"^(#+) {re.escape(heading)}\s*$", readme, flags=re.M)
if match is None:
    sys.exit(print(f"{sys.argv[1]} has no heading {heading!r}", file=sys.stderr) or 3)
level = len(match.group(1))
section = readme[match.end() :]
end = re.search(rf"^#{{1,{level}}} ", section, flags=re.M)  # the next heading of this level or up
section = section[: end.start()] if end else section
block = re.search(r"^```python\n(.*?)^```", section, flags=re.M | re.S)
if block is None:
    sys.exit(print(f"no ```python block under {heading!r}", file=sys.stderr) or 3)
print(block.group(1), end="")
