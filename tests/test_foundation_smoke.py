"""The tiny dataset builds and loads with the documented shapes."""
from data import dataset


def test_tiny_dataset_loads(tiny_dataset):
    meta = dataset.read_meta(tiny_dataset)
    for split in dataset.SPLITS:
        a = dataset.load(tiny_dataset, split)
        assert a["X"].shape[1:] == (meta["T_obs"], meta["N"] + 1, 2)
        assert len(a["X"]) == meta["splits"][split]["windows"] > 0
