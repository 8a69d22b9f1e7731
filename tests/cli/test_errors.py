"""Issue 23: a command line's mistake is refused before anything is built or written, in one line
that says what to do, without a traceback. Each case of bench/cli_errors.py runs in a fresh
process in an empty working directory, which must stay empty. The time bound here is a hang guard
far above the target (2 s on an idle 2-core machine), which `make bench ARGS=cli_errors`
measures."""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[2] / "bench" / "cli_errors.py"
_spec = importlib.util.spec_from_file_location("bench_cli_errors", BENCH)
bench = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bench)

# A generous bound, not the target (measured by the benchmark): 10 x the target, where the answer
# comes from files (and the checkpoint, or the head and the loss, with torch).
BOUND_S = 20
OPTIONS = "options: a, fisher, quat, sixd, svd9d"
KITTI = r"sequences/00/image_2, poses/00\.txt, sequences/02/image_2, poses/02\.txt and 12 more"
# case -> (exit code, the one line it ends with)
EXPECTED = {
    "misspelt key": (1, r"^rotlearn-train: config key optim\.lrr: unknown key; did you mean "
                     r"optim\.lr\?; allowed: lr, betas, eps, weight_decay, .* \(nothing was wr"),
    "misspelt key with +": (1, r"^rotlearn-train: config key optim\.lrr: unknown key; did you "
                            r"mean optim\.lr\?; allowed: lr, "),
    "a component's key at the top level": (1, r"^rotlearn-train: config key lr: unknown key; did "
                                           r"you mean optim\.lr\?; allowed: calibrate, "),
    "the README's misspelt key": (1, r"^rotlearn-train: config key data\.phi_maxdeg: unknown "
                                  r"key; did you mean data\.phi_max_deg\?; allowed: phi_max_deg"),
    "a misspelt key to delete": (1, r"^rotlearn-train: config key optim\.lrr: unknown key; did "
                                 r"you mean optim\.lr\?; allowed: .*lr, weight_decay; ~ deletes "
                                 r"a key it has \(nothing was written\)$"),
    "a misspelt key in a mapping": (1, r"^rotlearn-train: config key optim\.lrr: unknown key; "
                                    r"did you mean optim\.lr\?; allowed: lr, betas, eps, "),
    "unknown option": (1, rf"^rotlearn-train: config key rep: no option 'aa'; did you mean rep=a"
                       rf"\?; {OPTIONS} \(nothing was written\)$"),
    "a schema as an option": (1, rf"^rotlearn-train: config key rep: no option 'head_schema'; "
                              rf"{OPTIONS} \("),
    "no data root": (1, rf"^rotlearn-train: config key data\.root: no directory /nonexistent; "
                     rf"it must hold {KITTI} \(data/README\.md\)"),
    "incomplete dataset": (1, r"^rotlearn-train: config key data\.train_sequences: .*/kitti "
                           r"lacks sequences/02/image_2, poses/02\.txt, sequences/05/image_2, "
                           r"poses/05\.txt and 10 more \(data/README\.md\)"),
    "an override the grammar cannot read": (1, r"^rotlearn-train: config key optim\.lr: cannot "
                                            r"read 'optim\.lr=\[1' \(no viable alternative at "
                                            r"input '\[1'\); a value with brackets, .* is quoted"),
    "a run folder for a sweep": (1, r"^rotlearn-train: hydra\.run\.dir is not used: this "
                                 r"command runs a sweep, whose folder is hydra\.sweep\.dir; "
                                 r"nothing was written$"),
    "a sweep folder for one run": (1, r"^rotlearn-train: hydra\.sweep\.dir is not used: this "
                                   r"command runs one run, whose folder is hydra\.run\.dir; "
                                   r"nothing was written$"),
    "a misspelt key of Hydra's": (1, r"^rotlearn-train: config key hydra\.run\.dirr: unknown "
                                  r"key; did you mean hydra\.run\.dir\?; allowed: dir \(nothing"),
    "a setting of another launcher": (1, r"^rotlearn-train: config key hydra\.launcher\.n_jobs: "
                                      r"unknown key; allowed: _target_; n_jobs is a setting of "
                                      r"hydra/launcher=joblib \(nothing was written\)$"),
    "a sweep's config asked for": (1, r"^rotlearn-train: -m and --cfg do not go together \(Hydra "
                                   r"takes one of .*rotlearn-train <its values> --cfg job$"),
    "a sweep of Hydra's own settings": (1, r"^rotlearn-train: config key hydra\.sweeper\.params"
                                        r"\.trial: Hydra's own settings take one value, not a "
                                        r"sweep; to sweep trial: trial='range\(0,5\)'; a value"),
    "value out of range": (1, r"^rotlearn-train: config key data\.batch_size: should be greater "
                           r"than 0, got 0 \(nothing was written\)$"),
    "no demo data": (1, r"^rotlearn-train: config key data\.root: no directory data/demo/mav; it "
                     r"must hold flea3/data\.csv, .*; make it: rotlearn-make-demo-data --out "
                     r"data/demo --only mav \(nothing was written\)$"),
    "no data root of this format": (1, r"^rotlearn-train: config key data\.root: no directory "
                                    r"/nonexistent; it must hold train, test \(data/README\.md\)"
                                    r" \(nothing was written\)$"),  # format=pts; not <synset>
    # a sweep: each job checked before the first runs (only its first values were)
    "a misspelt option in a sweep": (1, rf"^rotlearn-train: config key rep: no option 'sixx'; "
                                     rf"did you mean rep=sixd\?; {OPTIONS} \(nothing was wr"),
    "a sweep's second value out of range": (1, r"^rotlearn-train: config key data\.phi_max_deg: "
                                            r"should be less than or equal to 180, got 270 \("),
    "sweep values that do not go together": (1, r"^rotlearn-train: config key loss\.rep: loss="
                                             r"bingham needs a head that defines a belief \(rep="
                                             r"a or rep=fisher\); rep=sixd does not \(nothing"),
    "a value of the wrong type": (1, r"^rotlearn-train: config key optim\.lr: should be a valid "
                                  r"number, got 'abc' \(nothing was written\)$"),
    "a Trainer value out of range": (1, r"^rotlearn-train: config key trainer\.max_epochs: must "
                                     r"be a positive integer \(Lightning reads -1 as 'train "
                                     r"forever', 0 as no training\), got 0 \(nothing was"),
    "an accelerator the machine lacks": (1, r"^rotlearn-train: config key trainer\.accelerator: "
                                         r"tpu asks for a device this machine does not have; on "
                                         r"its CPU: trainer=cpu or trainer\.accelerator=auto \("),
    "null for a config group": (1, r"^rotlearn-train: config key logger: takes one of its "
                                r"options \(csv, none, tensorboard\), not null; leave logger= "
                                r"out for the config's own choice \(nothing was written\)$"),
    "a group the config chooses none of": (1, r"^rotlearn-train: config key variant: conf/train"
                                           r"\.yaml chooses no variant; experiment=beliefs "
                                           r"chooses one \(e\.g\. experiment=beliefs variant="),
    "calibrate without a belief": (1, r"^rotlearn-train: config key calibrate: fits the "
                                   r"temperature of a belief; rep=sixd has none"),
    "likelihood loss without a belief": (1, r"^rotlearn-train: config key loss\.rep: "
                                         r"loss=bingham needs a head that defines a belief \(rep="
                                         r"a or rep=fisher\); rep=sixd does not"),
    "eval without ckpt": (1, r"^rotlearn-eval: ckpt=<run directory or \.ckpt file> is missing"),
    "eval with an empty ckpt": (1, r"^rotlearn-eval: ckpt is empty; pass a run directory or "
                                r"a \.ckpt file$"),
    "eval with an unclosed list of runs": (1, r"^rotlearn-eval: ckpt: \[.*not_a_run,.*sweep is "
                                           r"not a list of runs \(no viable alternative"),
    "eval of a folder that is no run": (1, r"^rotlearn-eval: ckpt: .*not_a_run is not a rotlearn "
                                        r"run: it has no checkpoints/last\.ckpt"),
    "eval of a sweep directory": (1, r"^rotlearn-eval: ckpt: .*sweep is a sweep directory, not "
                                  r"one run: pass one of its jobs, .*sweep/0, .*sweep/1 \("),
    "eval with OOD on synthetic data": (1, r"^rotlearn-eval: config key ckpt: .* is no image-pair "
                                        r"run: .*SyntheticWahbaDataModule; to use its model: "
                                        r"rotlearn-predict"),
    "eval with a dataset option": (1, r"^rotlearn-eval: config key data: holds keys to set "
                                   r"one by one, data\.<key>=value \(root, num_workers, "
                                   r"eval_batch_size, corrupt_fraction\), not data=kitti \("),
    "eval with no mapping for ood": (1, r"^rotlearn-eval: config key ood: holds keys to set one "
                                     r"by one, ood\.<key>=value \(quantiles, .*\), not ood=null"),
    "predict with a folder that is no run": (2, r"^rotlearn-predict: .*not_a_run is not a "
                                             r"rotlearn run"),
    "predict with a folder of runs": (2, r"^rotlearn-predict: .*folders\d* holds runs, not one "
                                      r"run: pass one of them, .*synthetic_run$"),
    "predict with a sweep directory": (2, r"^rotlearn-predict: .*sweep is a sweep directory, not "
                                       r"one run: pass one of its jobs, .*sweep/0, .*sweep/1$"),
}  # fmt: skip


@pytest.fixture(scope="module")
def folders(tmp_path_factory) -> dict[str, str]:
    return bench.scenario(tmp_path_factory.mktemp("folders"))


def test_every_case_of_the_benchmark_is_checked():
    assert set(EXPECTED) == set(bench.CASES)


@pytest.mark.parametrize("case", bench.CASES)
def test_a_mistake_is_refused_in_one_line_writing_nothing(case, folders, tmp_path):
    done, seconds = bench.run(case, folders, cwd=tmp_path)
    code, message = EXPECTED[case]
    lines = done.stderr.strip().splitlines()
    assert done.returncode == code, done.stderr
    assert len(lines) == 1 and re.search(message, lines[0]), done.stderr
    assert "Traceback" not in done.stderr + done.stdout
    assert list(tmp_path.iterdir()) == []  # no run, eval or output directory
    assert seconds < BOUND_S


@pytest.mark.parametrize(
    ("argv", "said"),
    [
        (["-m", "rep=a,sixd", "--cfg", "job"], "-m and --cfg do not go together"),
        (["-mc", "job"], "-m and --cfg do not go together"),  # as Hydra's parser reads it
        (["--multi", "--cfg=job"], "-m and --cfg do not go together"),
        (["-m", "--info"], "-m and --info do not go together"),
        (["--resolve"], "--resolve goes with --cfg"),
        (["-m", "--cfg", "job", "--hydra-help"], None),  # help wins, as in Hydra
        (["rep=a", "--cfg", "job", "--resolve"], None),
        (["-m", "rep=a,sixd"], None),
        (["--cfg"], None),  # no value: Hydra's own message
    ],
)
def test_hydras_modes_are_read_as_hydra_reads_them(argv, said):
    from rotlearn.cli.train import _refuse_two_modes

    if said is None:
        _refuse_two_modes(argv)
        return
    with pytest.raises(SystemExit, match=rf"^rotlearn-train: {re.escape(said)}"):
        _refuse_two_modes(argv)
