# rotlearn: everyday commands. Every target builds .venv from nothing when it is missing or older
# than pyproject.toml, so `make train` and `make test` are the whole set-up on a fresh machine.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
ARGS   ?=

.DEFAULT_GOAL := help
.PHONY: help venv train test test-full lint format bench reproduce-cpu reproduce-ood reproduce-ood-quick reproduce-ood-ensembles reproduce-ood-paper-scale reproduce-beliefs demo-data tensorboard clean

help: ## list the targets
	@grep -E '^[a-z-]+:.*## ' $(MAKEFILE_LIST) | awk -F':.*## ' '{printf "  make %-12s %s\n", $$1, $$2}'
	@echo "  pass options with ARGS, e.g.  make train ARGS='rep=sixd optim.lr=1e-3'"

# constraints.txt pins the development environment to the local torch build (the package itself
# declares the range it supports); users install with plain `pip install rotlearn[...]`.
$(STAMP): pyproject.toml constraints.txt
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -c constraints.txt -e '.[dev]'
	@touch $@

venv: $(STAMP) ## create or refresh .venv (torch==2.13.0 CPU build, every extra, dev tools)

train: $(STAMP) ## train the default experiment (A head, synthetic Wahba data); ARGS=overrides
	$(BIN)/rotlearn-train $(ARGS)

# Test files run on every core (pytest-xdist), a whole file per worker so that its fixtures are made
# once: most end-to-end tests wait on a child process. JOBS=0: all in this one process.
JOBS ?= $(shell nproc 2>/dev/null || echo 2)

test: $(STAMP) ## fast test suite (under 10 minutes on 2 cores)
	$(BIN)/python -m pytest -m "not slow" -q -n $(JOBS) --dist loadfile $(ARGS)

test-full: $(STAMP) ## every test, the slow ones too
	$(BIN)/python -m pytest -q -n $(JOBS) --dist loadfile $(ARGS)

lint: $(STAMP) ## ruff lint and format check
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

format: $(STAMP) ## apply ruff fixes and formatting
	$(BIN)/ruff check --fix .
	$(BIN)/ruff format .

bench: $(STAMP) ## benchmarks: results as JSON under bench/results and a printed table
	$(BIN)/python bench/run.py $(ARGS)

.PHONY: docs
docs: $(STAMP) ## API documentation site in docs/_build/html (a warning fails the build)
	$(BIN)/sphinx-build -W --keep-going -q -b html docs docs/_build/html $(ARGS)
	@echo "open docs/_build/html/index.html"

reproduce-cpu: $(STAMP) ## paper Figs. 3 and 4 sized for this CPU (about 25 min), each with its report
	$(BIN)/rotlearn-train -m experiment=synthetic_lr_cpu trainer.enable_progress_bar=false \
		hydra.sweep.dir=outputs/reproduce-cpu/synthetic_lr_cpu
	$(BIN)/rotlearn-train -m experiment=synthetic_phi_max_cpu trainer.enable_progress_bar=false \
		hydra.sweep.dir=outputs/reproduce-cpu/synthetic_phi_max_cpu
	@echo "reports: outputs/reproduce-cpu/*/report.md"

reproduce-beliefs: $(STAMP) ## issue 17 beliefs on heteroscedastic data, CPU-sized (about 20-30 min), with report
	$(BIN)/rotlearn-train -m experiment=beliefs_cpu trainer.enable_progress_bar=false \
		hydra.sweep.dir=outputs/reproduce-beliefs
	@echo "report: outputs/reproduce-beliefs/report.md"

OOD := outputs/reproduce-ood
QUIET := trainer.enable_progress_bar=false
SEEDS := sweep=seeds
# $(call a_seeds,<experiment>,<loss>,<dir>): the A head on seeds 0, 1, 2 (model and data, <dir>/0..2),
# then their ensemble (the sum of the members' A; <dir>_ensemble)
define a_seeds
	$(BIN)/rotlearn-train -m experiment=$(1) rep=a loss=$(2) $(SEEDS) $(QUIET) hydra.sweep.dir=$(3)
	$(BIN)/rotlearn-eval 'ckpt=[$(3)/0,$(3)/1,$(3)/2]' hydra.run.dir=$(3)_ensemble
endef
# $(call ae_run,<data>,<dir>): the auto-encoder OOD baseline as its own run (<dir>/<data>_ae)
define ae_run
	$(BIN)/rotlearn-train experiment=$(1)_autoencoder_demo $(QUIET) hydra.run.dir=$(2)/$(1)_ae
endef
# $(call head_run,<data>,<rep>,<dir>,<more overrides>): one head on seed 0 (<dir>/<data>_<rep>)
define head_run
	$(BIN)/rotlearn-train experiment=$(1)_ood_demo rep=$(2) hydra.mode=RUN $(QUIET) $(4) \
		hydra.run.dir=$(3)/$(1)_$(2)
endef

reproduce-ood: $(STAMP) ## paper Table I (KITTI demo) and Fig. 8 (MAV demo), A rows on 3 seeds + ensembles, reports
	@test -d data/demo/kitti || $(BIN)/rotlearn-make-demo-data --out data/demo --only kitti
	@test -d data/demo/mav || $(BIN)/rotlearn-make-demo-data --out data/demo --only mav
	$(call ae_run,kitti,$(OOD))
	$(call head_run,kitti,quat,$(OOD))
	$(call head_run,kitti,sixd,$(OOD),callbacks.ood.autoencoder_ckpt=$(OOD)/kitti_ae)
	$(call a_seeds,kitti_ood_demo,bingham,$(OOD)/kitti_a_bingham)
	$(call a_seeds,kitti_ood_demo,chordal,$(OOD)/kitti_a_chordal)
	$(call ae_run,mav,$(OOD))
	$(call head_run,mav,sixd,$(OOD),callbacks.ood.autoencoder_ckpt=$(OOD)/mav_ae)
	$(call a_seeds,mav_ood_demo,bingham,$(OOD)/mav_a_bingham)
	$(call a_seeds,mav_ood_demo,chordal,$(OOD)/mav_a_chordal)
	$(BIN)/rotlearn-report $(OOD)/kitti_quat $(OOD)/kitti_sixd $(OOD)/kitti_a_bingham $(OOD)/kitti_a_chordal \
		$(OOD)/kitti_a_bingham_ensemble $(OOD)/kitti_a_chordal_ensemble --out $(OOD)/kitti
	$(BIN)/rotlearn-report $(OOD)/mav_sixd $(OOD)/mav_a_bingham $(OOD)/mav_a_chordal \
		$(OOD)/mav_a_bingham_ensemble $(OOD)/mav_a_chordal_ensemble --out $(OOD)/mav
	@echo "reports (ensembles beside the single runs: evaluated.members=3): $(OOD)/kitti/report.md (Table I), $(OOD)/mav/report.md (Fig. 8)"

reproduce-ood-quick: $(STAMP) ## Table I's A rows only (KITTI demo, chordal and Bingham, 3 seeds + ensembles), with report
	@test -d data/demo/kitti || $(BIN)/rotlearn-make-demo-data --out data/demo --only kitti
	$(call a_seeds,kitti_ood_demo,bingham,$(OOD)_quick/kitti_a_bingham)
	$(call a_seeds,kitti_ood_demo,chordal,$(OOD)_quick/kitti_a_chordal)
	$(BIN)/rotlearn-report $(OOD)_quick/kitti_a_bingham $(OOD)_quick/kitti_a_chordal \
		$(OOD)_quick/kitti_a_bingham_ensemble $(OOD)_quick/kitti_a_chordal_ensemble --out $(OOD)_quick/kitti
	@echo "report (ensembles beside the single runs: evaluated.members=3): $(OOD)_quick/kitti/report.md"

reproduce-ood-ensembles: $(STAMP) ## KITTI demo: A + Bingham on 9 seeds and their 3 ensembles of 3 seeds each (about 20 min), with report
	@test -d data/demo/kitti || $(BIN)/rotlearn-make-demo-data --out data/demo --only kitti
	$(BIN)/rotlearn-train -m experiment=kitti_ood_demo rep=a loss=bingham $(SEEDS) 'trial=range(0,9)' $(QUIET) \
		hydra.sweep.dir=$(OOD)_ensembles/kitti_a_bingham
	for k in 0 3 6; do $(BIN)/rotlearn-eval "ckpt=[$(OOD)_ensembles/kitti_a_bingham/$$k,$(OOD)_ensembles/kitti_a_bingham/$$((k+1)),$(OOD)_ensembles/kitti_a_bingham/$$((k+2))]" \
		hydra.run.dir=$(OOD)_ensembles/kitti_a_bingham_ensemble_$$k || exit 1; done
	$(BIN)/rotlearn-report $(OOD)_ensembles/kitti_a_bingham $(OOD)_ensembles/kitti_a_bingham_ensemble_0 \
		$(OOD)_ensembles/kitti_a_bingham_ensemble_3 $(OOD)_ensembles/kitti_a_bingham_ensemble_6 --out $(OOD)_ensembles/kitti
	@echo "report (9 single runs, 3 ensembles: evaluated.members=3): $(OOD)_ensembles/kitti/report.md"

reproduce-ood-paper-scale: $(STAMP) ## GPU: Table I's A head (chordal, Bingham) at the paper's scale, world written first (1.5 GB)
	@test -d data/paper_scale/kitti || $(BIN)/rotlearn-make-demo-data --out data/paper_scale --only kitti --scale paper --workers 9
	$(BIN)/rotlearn-train experiment=kitti_ood_paper_scale trainer=gpu $(QUIET) hydra.sweep.dir=$(OOD)_paper_scale
	@echo "report: $(OOD)_paper_scale/report.md"

demo-data: $(STAMP) ## write small datasets in the real layouts under data/demo
	$(BIN)/rotlearn-make-demo-data --out data/demo

tensorboard: $(STAMP) ## open TensorBoard on every run under outputs/
	$(BIN)/tensorboard --logdir outputs --bind_all

clean: ## remove the venv and caches (keeps outputs/ and data/)
	rm -rf $(VENV) .pytest_cache .ruff_cache .hypothesis build dist src/*.egg-info docs/_build
	find . -name __pycache__ -type d -prune -exec rm -rf {} +
