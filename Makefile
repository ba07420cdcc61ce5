# Every target sets itself up on a fresh machine: .venv, the CPU torch wheel, the project.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: setup run test test-compat bench reproduce beyond beyond-full variants baselines suites suites-reference figures clean

setup: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet torch==2.13.0
	$(PY) -m pip install --quiet -e '.[dev]'
	$(PY) -m ferl.mnist_download    # data=mnist_full's 60 000 + 10 000 images (11 MB, once per machine)
	touch $(STAMP)

# The default experiment (ch3_floor), then its figures and report.
run: $(STAMP)
	@dir=outputs/ch3_floor/$$(date +%Y-%m-%d_%H-%M-%S); \
	$(PY) train.py hydra.run.dir=$$dir && $(PY) analyze.py $$dir && \
	echo "ferl: make run's outputs are in $$dir/ (formats: docs/records.md)" && \
	echo "  config:      $$dir/.hydra/config.yaml" && \
	echo "  summary:     $$dir/summary.json" && \
	echo "  TensorBoard: tensorboard --logdir $$dir/tb" && \
	echo "  figures:     $$dir/analysis/*.png (their numbers: *.csv)" && \
	echo "  report:      $$dir/analysis/report.md (each dissertation claim beside what was measured)" && \
	echo "  checkpoints: $$dir/checkpoints/ (python train.py resume=true hydra.run.dir=$$dir)" && \
	echo "  records:     $$dir/records/ (what analysis reads)"

# Lint and layout (pyproject.toml's [tool.ruff]) and types ([tool.mypy]: ferl/ and hydra_plugins/) first: seconds, where the tests take minutes.
test: $(STAMP)
	$(PY) -m ruff check .     # lint rules: pyproject.toml [tool.ruff]
	$(PY) -m ruff format --check .  # one layout (ruff format, at the same line length)
	$(PY) -m mypy             # types: pyproject.toml [tool.mypy]
	$(PY) -m pytest -n 2 -q

# The whole dissertation: the nine experiments of docs/reproduction.md (the set of `experiment=glob(*)`,
# listed longest first so that the parallel jobs finish together), the training-noise grid of
# Fig. 3.6 (ch3_floor at 9 training levels; each run tests all 9 levels) and the hidden sizes of
# Fig. 3.13 (ch3_coding_cw with 10 and 40 hidden; 20 is in the first sweep), the long regular
# T-maze of Fig. 4.4 (corridor length 6: a random walk ends in exactly T_min = 6 steps with
# probability (1/4)^5 · 1/2 ≈ 5·10⁻⁴, so balancing the lengths 6 … 10 needs ~50× Table 4.1's
# 2 000 random episodes); then the sweep's aggregate tables, reproduction report, the README's
# scorecard and docs/reproduction.md's claims table (analyze.py --readme), and the README's gallery.
# The experiments first, REPRO_JOBS jobs at a time; then the other three sweeps at once
# (ferl/run/together.py), the noise grid REPRO_JOBS at a time and the two small sweeps one at a time,
# sharing the cores: one after another, a core idled through the one-job sweep and while each
# sweep's last job ran alone (docs/performance.md, "Sweeps at once"). Each sweep's whole output goes
# to <sweep>/sweep.log, its progress lines here.
REPRO_JOBS  ?= 2
# The sweep folder of the target being made (docs/sweeps.md, "Resuming a sweep"): a new
# outputs/<target>/<date>_<time>/ with its sweep.json (start, commit), or RESUME=<that folder> of an
# interrupted sweep of the same target: its finished jobs are kept, interrupted ones resume from their
# checkpoints, the others start; the analysis runs once at the end. RESUMING: ferl.run.together's flag.
SWEEP_DIR = dir=$$($(PY) -m ferl.run.sweepdir $@ "$(RESUME)") || exit 2
RESUMING  = $(if $(RESUME),--resume)
EXPERIMENTS := table5_1_pixel,table4_2_digit,table5_1_bit,table4_1_regular,table4_1_matching,ch3_floor,ch3_coding_cw,ch3_coding_ccw,ch3_coding_noreward
NOISE_GRID  := 0.0,0.125,0.25,0.375,0.5,0.625,0.75,0.875,1.0

reproduce: $(STAMP)
	@$(SWEEP_DIR); start=$$(date +%s); \
	$(PY) -m ferl.run.together $(RESUMING) $$dir "experiments $(REPRO_JOBS) experiment=$(EXPERIMENTS)" && \
	$(PY) -m ferl.run.together $(RESUMING) $$dir "noise_grid $(REPRO_JOBS) experiment=ch3_floor env.noise=$(NOISE_GRID)" \
	  "hidden_sizes 1 experiment=ch3_coding_cw actor.n_hidden=10,40" \
	  "long_corridor 1 experiment=table4_1_regular env.corridor_length=6 trainer.n_sample=100000" && \
	echo $$(( $$(date +%s) - start )) > $$dir/train_wall_time_s && \
	$(PY) analyze.py $$dir --readme README.md --readme docs/reproduction.md && \
	$(PY) docs/figures/gallery.py $$dir --readme README.md && \
	echo "  reproduced in $$(( $$(date +%s) - start )) s; report: $$dir/analysis/report.md"

# Beyond the dissertation (§5.4): (b) sample efficiency on the tasks
# BEYOND_EFFICIENCY (none: skipped), each by its phased algorithm, online, and online with
# curiosity; (a) the memory curves, trained online with
# BEYOND_EPISODES episodes (the curves compare memories, not budgets; fewer replayed episodes per
# update for the same reason): the regular T-maze with every memory at the corridor lengths
# BEYOND_CORRIDORS (T_max = 2 T_min + 4), the same maze with directed exploration
# (BEYOND_EXPLORATION: εz-greedy, the method that reached goals most often in docs/beyond.md's
# side-by-side) for BEYOND_EXPLORE_MEMORIES at BEYOND_EXPLORE_CORRIDORS (its runs without
# exploration are the first curve's), and the passive T-maze of Ni et al. (2023) for
# BEYOND_PASSIVE_MEMORIES at memory lengths BEYOND_PASSIVE_CORRIDORS (BEYOND_PASSIVE_EPISODES
# episodes, its experiment's other settings), and the same maze for the recurrent Q-learner, whose
# memory is learnt for reward (actor=recurrent_q, its cores BEYOND_Q_MEMORIES, linear head, β's end
# BEYOND_Q_BETA) at BEYOND_Q_CORRIDORS with BEYOND_Q_EPISODES episodes, compiled in graphs of a
# few steps whose compile time does not grow with T_max (docs/performance.md, "Graphs of fixed
# size"). Each curve job has BEYOND_RUNS runs, BEYOND_LONG_RUNS
# from corridor BEYOND_LONG_FROM on. Every sweep's jobs share REPRO_JOBS lanes in one queue
# (ferl/run/together.py --lanes), the phased sweep first (its pixel job fits the RBM that the
# online pixel jobs then load), then the longest, so that no core waits at a sweep's end; each job's output in <sweep>/<curve>/<job folder>.log. Then the sweep's report with its
# "beyond" section. A reduced
# version: e.g. make beyond BEYOND_PASSIVE_CORRIDORS="5 10" BEYOND_PASSIVE_MEMORIES=lstm,gru BEYOND_RUNS=2.
# `make beyond-full`: the same recipe with the full memory curves (below), into outputs/beyond_full/.
BEYOND_EFFICIENCY        ?= table5_1_pixel,table5_1_bit,table4_1_matching
BEYOND_EPISODES          ?= 2000
BEYOND_ETA               ?= 0.1
BEYOND_RUNS              ?= 10
BEYOND_LONG_RUNS         ?= 5
BEYOND_LONG_FROM         ?= 200
BEYOND_CORRIDORS         ?= 20 10 5 3
MEMORIES                 ?= elman,lstm,gru,esn,transformer
BEYOND_EXPLORATION       ?= ez_greedy
# The online sweep varies the task fastest: its two lanes then start different tasks, whose graphs
# compile side by side, and η = 0.1 finds η = 0's graphs compiled (one graph serves every η) where
# the task first would start η = 0 and 0.1 together, one lane waiting on the other's compiling.
# The defaults end each curve at its first length where no memory solved a run on 2026-12-07
# (the active maze at 20, the passive at L = 20, the exploration curve at 10): 27.4 min on 2 cores
# from an empty compile cache (docs/beyond.md). `make beyond-full` runs the full lists
# (docs/beyond.md, "Memory curves", gives their cost)
BEYOND_EXPLORE_CORRIDORS ?= 10 5
BEYOND_EXPLORE_MEMORIES  ?= lstm,gru
BEYOND_PASSIVE_CORRIDORS ?= 20 10
BEYOND_PASSIVE_MEMORIES  ?= lstm,gru
BEYOND_PASSIVE_EPISODES  ?= 2000
BEYOND_Q_CORRIDORS       ?= 50
BEYOND_Q_MEMORIES        ?= lstm,gru
BEYOND_Q_EPISODES        ?= 10000
BEYOND_Q_BETA            ?= 30

# The full memory curves: the passive maze at L = 500 … 10 and the active maze at corridors 50 … 5,
# with and without directed exploration, each with every memory (MEMORIES), 10 000 passive episodes;
# no sample-efficiency sweeps. Target-specific: any of them set on the command line wins.
beyond-full: BEYOND_EFFICIENCY        =
beyond-full: BEYOND_CORRIDORS         = 50 20 10 5
beyond-full: BEYOND_EXPLORE_CORRIDORS = 50 20 10 5
beyond-full: BEYOND_EXPLORE_MEMORIES  = $(MEMORIES)
beyond-full: BEYOND_PASSIVE_CORRIDORS = 500 200 100 50 20 10
beyond-full: BEYOND_PASSIVE_MEMORIES  = $(MEMORIES)
beyond-full: BEYOND_PASSIVE_EPISODES  = 10000

beyond beyond-full: $(STAMP)
	@$(SWEEP_DIR); start=$$(date +%s); specs=""; \
	sweep() { case $$1 in .) name=$$2;; *) name=$$1/$$2;; esac; specs="$$specs '$$name 1 $$3'"; }; \
	runs() { if [ $$1 -ge $(BEYOND_LONG_FROM) ]; then echo $(BEYOND_LONG_RUNS); else echo $(BEYOND_RUNS); fi; }; \
	if [ -n "$(BEYOND_EFFICIENCY)" ]; then sweep . phased "experiment=$(BEYOND_EFFICIENCY)"; fi; \
	for c in $(BEYOND_Q_CORRIDORS); do \
	  sweep passive_q_curve corridor_$$c "experiment=passive_tmaze trainer=algorithm1 predictor=none \
	    actor=recurrent_q actor.head=linear actor.memory=$(BEYOND_Q_MEMORIES) actor.beta.end=$(BEYOND_Q_BETA) \
	    env.corridor_length=$$c trainer.n_episodes=$(BEYOND_Q_EPISODES) n_runs=$$(runs $$c)"; \
	done; \
	if [ -n "$(BEYOND_EFFICIENCY)" ]; then \
	  sweep . online "trainer.curiosity=0,$(BEYOND_ETA) experiment=$(BEYOND_EFFICIENCY) trainer=online"; \
	fi; \
	for c in $(BEYOND_PASSIVE_CORRIDORS); do \
	  sweep passive_curve corridor_$$c "experiment=passive_tmaze predictor.joint.memory=$(BEYOND_PASSIVE_MEMORIES) \
	    env.corridor_length=$$c trainer.n_episodes=$(BEYOND_PASSIVE_EPISODES) n_runs=$$(runs $$c)"; \
	done; \
	for c in $(BEYOND_CORRIDORS); do \
	  sweep memory_length corridor_$$c "experiment=table4_1_regular trainer=online predictor.joint.memory=$(MEMORIES) \
	    env.corridor_length=$$c env.max_steps=$$((2 * c + 4)) trainer.n_episodes=$(BEYOND_EPISODES) \
	    trainer.replay_sample=16 n_runs=$$(runs $$c)"; \
	done; \
	for c in $(BEYOND_EXPLORE_CORRIDORS); do \
	  sweep exploration_curve corridor_$$c "experiment=table4_1_regular trainer=online \
	    predictor.joint.memory=$(BEYOND_EXPLORE_MEMORIES) exploration=$(BEYOND_EXPLORATION) \
	    env.corridor_length=$$c env.max_steps=$$((2 * c + 4)) trainer.n_episodes=$(BEYOND_EPISODES) \
	    trainer.replay_sample=16 n_runs=$$(runs $$c)"; \
	done; \
	eval "set -- $$specs"; \
	$(PY) -m ferl.run.together $(RESUMING) --lanes $(REPRO_JOBS) $$dir "$$@" && \
	echo $$(( $$(date +%s) - start )) > $$dir/train_wall_time_s && \
	$(PY) analyze.py $$dir && \
	echo "  $@ in $$(( $$(date +%s) - start )) s; report: $$dir/analysis/report.md"

# Beyond the dissertation (§5.4, II): the dissertation's agent beside its variants, each task run
# by every agent with 10 runs: the actor's value forms (actor.q) on the floor, the matching maze
# and the pixel maze; the DBN preprocessor on the pixel maze; the Gaussian-visible RBM and the
# binary RBM on the continuous (grey-level + Gaussian noise) pixel maze; Sallans & Hinton's
# large-action task. Then the report, whose "Agents side by side" section has a table and a
# learning-curve figure per task.
VALUE_FORMS := free_energy,scaled_free_energy,expected_energy

variants: $(STAMP)
	@dir=outputs/variants/$$(date +%Y-%m-%d_%H-%M-%S); start=$$(date +%s); \
	jobs="hydra/launcher=joblib hydra.launcher.n_jobs=$(REPRO_JOBS)"; \
	$(PY) train.py -m experiment=table5_1_pixel,table4_1_matching,ch3_floor actor.q=$(VALUE_FORMS) $$jobs \
	  hydra.sweep.dir=$$dir/value_forms && \
	$(PY) train.py -m experiment=table5_1_pixel_dbn,table5_1_pixel_gaussian,large_action,large_action_key_states $$jobs \
	  hydra.sweep.dir=$$dir/preprocessors_actions && \
	$(PY) train.py experiment=table5_1_pixel_gaussian preprocessor=rbm hydra.run.dir=$$dir/binary_rbm_on_grey && \
	echo $$(( $$(date +%s) - start )) > $$dir/train_wall_time_s && \
	$(PY) analyze.py $$dir && \
	echo "  variants in $$(( $$(date +%s) - start )) s; report: $$dir/analysis/report.md"

# Baselines side by side (docs/beyond.md, "Baselines side by side"): the dissertation's agent, memoryless FERL, the
# feed-forward Q-network on the same predictors (actor=mlp_q), a DRQN-style recurrent Q-learner and
# the oracle on the true state, on the floor, the matching maze (Algorithms 1 and 2), the pixel maze
# and the corridor-20 regular maze, 10 runs each, REPRO_JOBS at a time; RecurrentPPO (sb3-contrib)
# on the matching and corridor-20 mazes where the `baselines` extra is installed. Then the report,
# whose "Agents side by side" section has a table, a finding and a figure per task.
BASELINES_STAMP := $(VENV)/.installed-baselines
$(BASELINES_STAMP): $(STAMP)
	$(PY) -m pip install --quiet -e '.[baselines]'
	touch $@
baselines: $(BASELINES_STAMP)
	@$(SWEEP_DIR); start=$$(date +%s); \
	echo "ferl: sweep 1/1: side_by_side (every agent on every task, $(REPRO_JOBS) at a time)" && \
	$(PY) baselines/side_by_side.py $$dir --jobs $(REPRO_JOBS) && \
	echo "  baselines in $$(( $$(date +%s) - start )) s; report: $$dir/analysis/report.md"

# ferl's agents on third-party POMDPs through env=gymnasium (docs/beyond.md, "Outside POMDPs"): POPGym's RepeatPrevious,
# CountRecall, Autoencode and MineSweeper (Easy) and MiniGrid's MemoryS7, FERL online, MLP-Q,
# memoryless FERL and DRQN, 10 runs each, REPRO_JOBS at a time (the `suites` and `baselines` extras);
# then one table and one learning-curve figure per environment in the report, with RecurrentPPO's rows
# from the newest `make suites-reference` (copied in; the report names its folder, date and commit, or
# says there is none). `make suites-reference`: RecurrentPPO alone on the same environments, into
# outputs/suites_reference/<date>_<time>/ with its sweep.json (date, commit); no report of its own.
SUITES_STAMP := $(VENV)/.installed-suites
$(SUITES_STAMP): $(STAMP)
	$(PY) -m pip install --quiet -e '.[suites,baselines]'
	touch $@
suites: $(SUITES_STAMP)
	@$(SWEEP_DIR); start=$$(date +%s); \
	$(PY) baselines/suites.py $$dir --jobs $(REPRO_JOBS) && \
	echo "  suites in $$(( $$(date +%s) - start )) s; report: $$dir/analysis/report.md"

suites-reference: $(SUITES_STAMP)
	@$(SWEEP_DIR); start=$$(date +%s); \
	$(PY) baselines/suites.py $$dir --reference --jobs $(REPRO_JOBS) && \
	echo "  suites-reference in $$(( $$(date +%s) - start )) s: $$dir (make suites' reports read the newest)"

# ferl inside a user's own torch (docs/usage.md, "Installing into your own stack"): for each torch of
# COMPAT_TORCH, by default the oldest that pyproject.toml admits and the newest pip offers here (2.14.1,
# the cap of /etc/xdg/pip), a throwaway venv under a temp dir (removed after) with that torch, then
# `pip install -e .` (which must keep it: checked), then the suite's fast part, COMPAT_TESTS: the
# numerics of the RBM, actor and predictors against their references, the compiled fast path against
# eager, and the set-up checks. The golden numbers (tests/test_golden.py) are exact only under the torch
# that made them, 2.13.0 (`make test`), and are left out: under another torch the learning results
# agree in distribution, not bit for bit: tests/compat_learning.py runs a reduced-scale T-maze job of
# 10 runs under 2.13.0 once and under each torch, and their solved counts must agree within their
# s.e.m. COMPAT_TORCH=2.14.1 runs one leg.
COMPAT_TORCH ?= 2.8.0 2.14.1
COMPAT_TESTS ?= tests/test_rbm.py tests/test_actor.py tests/test_predictor.py tests/test_cpu_kernels.py \
                tests/test_numpy_reference.py tests/test_schedules.py tests/test_compile.py tests/test_fast_path.py \
                tests/test_env_options.py
test-compat: $(STAMP)
	@ref=$$(mktemp -d -t ferl-compat-ref-XXXXXX); \
	echo "ferl: test-compat: the reduced-scale learning job under the pinned torch, in $$ref"; \
	$(PY) tests/compat_learning.py run $$ref/learn || { status=$$?; rm -rf $$ref; exit $$status; }; \
	for v in $(COMPAT_TORCH); do \
	  tmp=$$(mktemp -d -t ferl-compat-XXXXXX); venv=$$tmp/venv; start=$$(date +%s); \
	  echo "ferl: test-compat: torch $$v in $$venv"; \
	  $(PYTHON) -m venv $$venv && \
	  $$venv/bin/python -m pip install --quiet torch==$$v && \
	  $$venv/bin/python -m pip install --quiet -e . pytest hypothesis && \
	  $$venv/bin/python -c "import sys, torch; v = torch.__version__.split('+')[0]; \
	    sys.exit(None if v == '$$v' else f'ferl: test-compat: pip install -e . replaced torch $$v by {v}')" && \
	  $$venv/bin/python -m pytest -q -p no:cacheprovider $(COMPAT_TESTS) && \
	  $$venv/bin/python tests/compat_learning.py run $$tmp/learn && \
	  $(PY) tests/compat_learning.py compare $$ref/learn $$tmp/learn; status=$$?; \
	  rm -rf $$tmp; echo "ferl: test-compat: torch $$v: exit $$status in $$(( $$(date +%s) - start )) s"; \
	  [ $$status -eq 0 ] || { rm -rf $$ref; exit $$status; }; \
	done; \
	rm -rf $$ref

bench: $(STAMP)
	$(PY) benchmarks/bench_floor.py
	$(PY) benchmarks/bench_preprocessor.py
	$(PY) benchmarks/bench_tmaze.py
	$(PY) benchmarks/bench_predictor.py

# The README's gallery (docs/figures/): figures of the newest analysed `make reproduce`, or of
# REPRODUCE_DIR=outputs/reproduce/<date>_<time>; `make reproduce` ends with it.
figures: $(STAMP)
	$(PY) docs/figures/gallery.py $(REPRODUCE_DIR) --readme README.md

clean:
	rm -rf $(VENV) outputs/*/ .pytest_cache
