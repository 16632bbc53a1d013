"""The README's Python examples run as written."""

import re
from pathlib import Path


def test_readme_examples_run(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # the examples write files (campaign.pt) here
    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", readme, re.S)
    assert len(blocks) >= 2
    namespace: dict = {}
    for block in blocks:  # later blocks reuse the names of earlier ones
        exec(compile(block, "README.md", "exec"), namespace)
    assert namespace["pred"].shape == (20, 11, 2)
    assert len(namespace["plan"].indices) == 9
    campaign = namespace["campaign"]
    assert campaign.num_experiments == 6 and (tmp_path / "campaign.pt").is_file()
