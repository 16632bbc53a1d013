"""The README's Python examples run as written."""

import re
from pathlib import Path


def test_readme_examples_run(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # the examples write files (campaign.pt) here
    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", readme, re.S)
    assert len(blocks) == 2  # the whole loop, and real measurements; the rest lives in the docs
    namespace: dict = {}
    for block in blocks:  # later blocks reuse the names of earlier ones
        exec(compile(block, "README.md", "exec"), namespace)
    campaign = namespace["campaign"]
    assert campaign.num_experiments == 11  # the lab's 8 and the 3 asked
    assert namespace["bands"].samples.shape == (64, 20, 21, 2)
    assert namespace["model"].calibration_ is not None
    assert (tmp_path / "lab.csv").is_file()
    lower, upper = namespace["new_measurements"].interval(0.9)
    assert lower.shape == (1, 30, 1) and bool((lower > 0).all() and (upper > lower).all())
    assert namespace["fit"].noise_.name == "relative"
