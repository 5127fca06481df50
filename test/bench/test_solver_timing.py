from vbrl_ros.bench.solver import time_gram_training, time_one_iteration


def test_time_one_iteration_small():
    out = time_one_iteration(n=30, d=200, c=2)
    assert out["fast_path"] == "woodbury" and out["max_rel_diff"] < 1e-8
    assert out["fast_s"] > 0 and out["literal_s"] > 0


def test_time_gram_training_small():
    out = time_gram_training(n=300, d=120, c=2, chunk=100)
    assert out["n"] == 300 and out["total_s"] > 0
    assert out["objective"] <= out["result"].objective_history[0]
