"""rotlearn.logs."""

import logging

from rotlearn.logs import logger_at_least, progress


def test_logger_at_least_quiets_tensorboards_reader_and_restores_its_level(tmp_path, caplog):
    """The sweep report reads event files under logger_at_least("tensorboard"): no INFO lines."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
    from torch.utils.tensorboard import SummaryWriter

    for step in range(2):  # two event files, as fitting then testing leave them
        with SummaryWriter(tmp_path, filename_suffix=f".{step}") as writer:
            writer.add_scalar("val/err_mean", float(step), step)
    with caplog.at_level(logging.INFO), logger_at_least("tensorboard"):
        events = EventAccumulator(str(tmp_path)).Reload()
    assert len(events.Scalars("val/err_mean")) == 2
    assert not [r for r in caplog.records if r.name.startswith("tensorboard")]
    with caplog.at_level(logging.INFO):  # outside, TensorBoard's own level again
        EventAccumulator(str(tmp_path)).Reload()
    assert any("Directory watcher" in r.getMessage() for r in caplog.records)


def test_progress_draws_a_bar_only_where_the_trainers_is_on():
    import lightning.pytorch as pl
    from tqdm.auto import tqdm

    batches = [1, 2, 3]
    quiet = pl.Trainer(enable_progress_bar=False, logger=False, enable_checkpointing=False)
    assert progress(batches, "scoring", quiet) is batches
    shown = progress(batches, "scoring", pl.Trainer(logger=False, enable_checkpointing=False))
    assert isinstance(shown, tqdm) and list(shown) == batches
    assert isinstance(progress(batches, "scoring"), tqdm)  # no trainer: shown
