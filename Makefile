# Two entry points: `make demo` and `make test`. Both create .venv when missing
# and (re)install only when pyproject.toml or constraints.txt changed.
PY      ?= python3
VENV    := .venv
STAMP   := $(VENV)/.installed
PIP     := $(VENV)/bin/python -m pip

.PHONY: demo test lint bench mutate mutate-sample clean

$(VENV)/bin/python:
	$(PY) -m venv $(VENV)

$(STAMP): $(VENV)/bin/python pyproject.toml constraints.txt
	$(PIP) install --quiet --disable-pip-version-check -c constraints.txt -e ".[all,dev,bench,zoo,ros,mutate]"
	touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/python -m agents.demo --out out/demo

test: $(STAMP)
	$(VENV)/bin/python -m pytest -q

lint: $(STAMP)
	$(VENV)/bin/ruff check . && $(VENV)/bin/ruff format --check .

bench: $(STAMP)
	$(VENV)/bin/python benchmarks/bench_env.py

# Mutation testing (outside `make test`; hours on 2 cores): the configuration is
# [tool.mutmut] in pyproject.toml; a run's score goes to docs/results/mutation/full/ (or
# sampled/), and combine.py there scores every module by its latest run in full. Both targets go
# on where a stopped run of the same code left off, and start afresh on any other code
# (docs/results/mutation/mutate_sample.py).
mutate: $(STAMP)
	$(VENV)/bin/python docs/results/mutation/mutate_sample.py --max-children $$(nproc) --fraction 1

# The same in less time (on 2026-12-05: 2,540 mutants in 87 min on 2 cores, most of it
# mutants stopped by mutmut's CPU-time limit): the filters and the service's limits completely, a seeded
# random tenth of every other module's mutants (sample.py), and the killed ratio over all
# mutants estimated from it with its 95 % interval (summarise.py).
mutate-sample: $(STAMP)
	$(VENV)/bin/python docs/results/mutation/mutate_sample.py --max-children $$(nproc) --fraction 0.1 --seed 0

clean:
	rm -rf $(VENV) out mutants
