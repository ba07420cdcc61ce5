"""``make test-compat``'s learning check (tests/compat_learning.py): solved counts compared within the
sum of their s.e.m., the s.e.m. of a count against its formula, √n · sd of the 0/1 verdicts."""

import json
import math

import pytest

from compat_learning import compare, solved


def job(folder, verdicts, torch="2.13.0"):
    folder.mkdir()
    (folder / "summary.json").write_text(json.dumps({"metrics": {"solved": verdicts}}))
    (folder / "torch.txt").write_text(torch)
    return folder


def test_the_s_e_m_of_a_solved_count_is_sqrt_n_times_the_sd_of_the_verdicts(tmp_path):
    verdicts = [1] * 7 + [0] * 3
    mean = 0.7
    sd = math.sqrt(sum((v - mean) ** 2 for v in verdicts) / 9)
    assert solved(job(tmp_path / "a", verdicts)) == (7, pytest.approx(math.sqrt(10) * sd), 10, "2.13.0")


@pytest.mark.parametrize(
    ("reference", "other", "agree"),
    [
        ([1] * 10, [1] * 10, True),  # 10 ± 0 and 10 ± 0
        ([1] * 10, [1] * 9 + [0], True),  # 1 apart, within 0 + 1.0
        ([1] * 10, [1] * 5 + [0] * 5, False),  # 5 apart, beyond 0 + 1.67
        ([1] * 8 + [0] * 2, [1] * 6 + [0] * 4, True),  # 2 apart, within 1.33 + 1.63
        ([1] * 9 + [0], [1] * 6 + [0] * 4, False),  # 3 apart, beyond 1.0 + 1.63
    ],
)
def test_solved_counts_agree_within_their_s_e_m(tmp_path, capsys, reference, other, agree):
    assert compare(job(tmp_path / "ref", reference), job(tmp_path / "other", other, "2.8.0")) is agree
    line = capsys.readouterr().out
    assert line.startswith("ferl: test-compat: solved") and ("agree within" in line) is agree
