# rotlearn: everyday commands. Every target builds .venv from nothing when it is missing or older
# than pyproject.toml, so `make train` and `make test` are the whole set-up on a fresh machine.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
ARGS   ?=

.DEFAULT_GOAL := help
.PHONY: help venv train test test-full lint format bench reproduce-cpu reproduce-ood reproduce-beliefs demo-data tensorboard clean

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

test: $(STAMP) ## fast test suite (under 10 minutes on 2 cores)
	$(BIN)/python -m pytest -m "not slow" -q $(ARGS)

test-full: $(STAMP) ## every test, the slow ones too
	$(BIN)/python -m pytest -q $(ARGS)

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

reproduce-beliefs: $(STAMP) ## issue 17 beliefs on heteroscedastic data, CPU-sized (about 20 min), with report
	$(BIN)/rotlearn-train -m experiment=beliefs_cpu trainer.enable_progress_bar=false \
		hydra.sweep.dir=outputs/reproduce-beliefs
	@echo "report: outputs/reproduce-beliefs/report.md"

OOD := outputs/reproduce-ood
reproduce-ood: $(STAMP) ## paper Table I (KITTI demo) and Fig. 8 (MAV demo), about 40 min, with reports
	@test -d data/demo/kitti || $(BIN)/rotlearn-make-demo-data --out data/demo --only kitti
	@test -d data/demo/mav || $(BIN)/rotlearn-make-demo-data --out data/demo --only mav
	$(BIN)/rotlearn-train -m experiment=kitti_ood_demo trainer.enable_progress_bar=false \
		hydra.sweep.dir=$(OOD)/kitti_ood_demo
	$(BIN)/rotlearn-train experiment=kitti_ood_demo rep=a loss=bingham hydra.mode=RUN \
		trainer.enable_progress_bar=false hydra.run.dir=$(OOD)/kitti_ood_demo_bingham
	$(BIN)/rotlearn-train -m experiment=mav_ood_demo trainer.enable_progress_bar=false \
		hydra.sweep.dir=$(OOD)/mav_ood_demo
	$(BIN)/rotlearn-report $(OOD)/kitti_ood_demo $(OOD)/kitti_ood_demo_bingham
	$(BIN)/rotlearn-report $(OOD)/mav_ood_demo
	@echo "reports: $(OOD)/kitti_ood_demo/report.md (Table I), $(OOD)/mav_ood_demo/report.md (Fig. 8)"

demo-data: $(STAMP) ## write small datasets in the real layouts under data/demo
	$(BIN)/rotlearn-make-demo-data --out data/demo

tensorboard: $(STAMP) ## open TensorBoard on every run under outputs/
	$(BIN)/tensorboard --logdir outputs --bind_all

clean: ## remove the venv and caches (keeps outputs/ and data/)
	rm -rf $(VENV) .pytest_cache .ruff_cache .hypothesis build dist src/*.egg-info docs/_build
	find . -name __pycache__ -type d -prune -exec rm -rf {} +
