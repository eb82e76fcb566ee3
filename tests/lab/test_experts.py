from lab.experts import ExpertScore, expert_table


def test_the_expert_table_names_its_command_seeds_and_failures():
    scores = [
        ExpertScore("lift-cube", "LiftExpert", 4, 3, 101.5, 300, 1000, (1002,)),
        ExpertScore("open-drawer", "DrawerExpert", 4, 4, 80.0, 250, 1000, ()),
    ]
    table = expert_table(scores, "hitl experts --episodes 4 --seed 1000")
    assert "Measured with `hitl experts --episodes 4 --seed 1000` (seeds 1000..1003" in table
    assert "| `lift-cube` | LiftExpert | 3/4 | 75% | 101.5 | 300 | 1002 |" in table
    assert "| `open-drawer` | DrawerExpert | 4/4 | 100% | 80.0 | 250 | - |" in table
    assert scores[0].rate == 0.75
