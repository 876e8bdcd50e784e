"""``aisdf bench rooms``: its table is the mean over seeds of each method's error per split,
with the served answer's ratios to the 2 cm voxel map and to the answer without the prior
(a run itself takes minutes: a bench, not a test)."""

from aisdf.bench import rooms


def fake(seed, served, noprior, v2, v5, shares=(1.0, 0.2)):
    e = lambda a: {"all": a, "unobserved": 2 * a}  # noqa: E731
    return {"seed": seed, "shares": {"all": shares[0], "unobserved": shares[1]},
            "error_cm": {"served": e(served), "served-noprior": e(noprior), "voxel-2cm": e(v2), "voxel-5cm": e(v5)}}


def test_table_means_over_seeds_and_ratios():
    md = rooms.table([fake(1, 1.0, 2.0, 2.0, 4.0), fake(2, 3.0, 4.0, 2.0, 4.0, (1.0, 0.4))])
    lines = md.splitlines()
    assert lines[0] == "| method | all (cm) | unobserved (cm) |"
    assert "| AiSDF served | 2.00 | 4.00 |" in lines
    assert "| AiSDF served, no prior | 3.00 | 6.00 |" in lines
    assert "| served / voxel 2 cm | 1.00x | 1.00x |" in lines
    assert "| served / no prior | 0.67x | 0.67x |" in lines
    assert "| share of points | 100.0 % | 30.0 % |" in lines
