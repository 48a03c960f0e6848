# The two commands a newcomer needs: `make demo` and `make test`.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
DEMO   := demo-out

.PHONY: demo test test-integration install install-test bench bench-peers clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip

# Installs are re-run only when pyproject.toml changes (stamp files).
# (pip's own lines show it moving: the first install takes a minute or two)
$(VENV)/.installed: pyproject.toml | $(BIN)/python
	@echo "== installing mosaicmap and its dependencies into $(VENV) (pip; a minute or two the first time)"
	$(BIN)/pip install --progress-bar off -e .
	touch $@

$(VENV)/.installed-test: pyproject.toml | $(BIN)/python
	@echo "== installing mosaicmap with its test dependencies into $(VENV) (pip; a minute or two the first time)"
	$(BIN)/pip install --progress-bar off -e '.[test]'
	touch $@ $(VENV)/.installed

install: $(VENV)/.installed
install-test: $(VENV)/.installed-test

# The nightly job end to end on an embedded default (a local map repository, simulated
# drive logs): day 1 is built and published as version 1; day 2 (the same floor driven
# again, five floor changes, 20 % darker) is built incrementally as version 2. Then the two
# versions are diffed against the simulator's truth, and version 1 is exported as a vehicle
# bundle with the delta that brings it to version 2 (applied and verified), and a vehicle
# replays a held-out log (another route, noisier) against the version-2 bundle. Bundles are
# signed with the map owner's key (made by `mosaicmap keys new`); the vehicle side
# (apply-delta, verify, track) trusts its public key only. Then an
# omnidirectional camera: two runs of a route through a room are built into one map (a
# floor from their bird's-eye views and a route panorama), exported, and a night run is
# tracked against it. Prints summaries, the map's log, and where the pictures and pages are.
# Every step prints a header line ("== step 3/12: ..."), then its own progress (a bar on a
# terminal; a line every few seconds in a log) and its summary. About 3.5 minutes on 2 idle
# cores (196 s, 2026-12-02); several times that when the cores are shared.
demo: install
	rm -rf $(DEMO)
	@echo "== step 1/12: simulate day 1: a robot drives a 5 x 5 m floor (~6 s on an idle machine)"
	$(BIN)/mosaicmap simulate floor $(DEMO)/logs/day1 --seed 1 --area 5x5
	@echo "== step 2/12: build day 1 and publish it as version 1 of the map (~20 s)"
	$(BIN)/mosaicmap build $(DEMO)/logs/day1 --map $(DEMO)/map --workdir $(DEMO)/work1 --report $(DEMO)/report1.json --tag day1
	$(BIN)/python -m pipeline.summary $(DEMO)/report1.json
	@echo "== step 3/12: simulate day 2: the same floor driven again, 5 floor changes, 20 % darker (~5 s)"
	$(BIN)/mosaicmap simulate floor $(DEMO)/logs/day2 --world $(DEMO)/logs/day1 --changes 5 --illumination 0.8 --seed 12
	@echo "== step 4/12: build day 2 incrementally as version 2 (~20 s)"
	$(BIN)/mosaicmap build $(DEMO)/logs/day2 --map $(DEMO)/map --workdir $(DEMO)/work2 --report $(DEMO)/report2.json --tag day2
	$(BIN)/python -m pipeline.summary $(DEMO)/report2.json
	@echo "== step 5/12: the map's versions and a quick look at the latest"
	$(BIN)/mosaicmap log $(DEMO)/map
	$(BIN)/mosaicmap quicklook $(DEMO)/map --annotate --out $(DEMO)/quicklook.png
	@echo "== step 6/12: what changed from day 1 to day 2, checked against the simulator's truth"
	$(BIN)/mosaicmap diff $(DEMO)/map day1 day2 --out $(DEMO)/diff --truth $(DEMO)/logs/day2/world/changes.png
	@echo "== step 7/12: the map owner's key; a signed bundle of version 1 and the delta to version 2"
	$(BIN)/mosaicmap keys new $(DEMO)/keys/owner.key
	$(BIN)/mosaicmap export $(DEMO)/map --version day1 $(DEMO)/bundles/day1.zip --sign $(DEMO)/keys/owner.key
	$(BIN)/mosaicmap export $(DEMO)/map --since day1 $(DEMO)/bundles/day1-to-day2.zip --sign $(DEMO)/keys/owner.key
	@echo "== step 8/12: the vehicle side: apply the delta, verify, and track a held-out run (~6 s)"
	$(BIN)/mosaicmap apply-delta $(DEMO)/bundles/day1.zip $(DEMO)/bundles/day1-to-day2.zip $(DEMO)/bundles/day2.zip --key $(DEMO)/keys/owner.key.pub
	$(BIN)/mosaicmap verify $(DEMO)/bundles/day2.zip --key $(DEMO)/keys/owner.key.pub
	$(BIN)/mosaicmap simulate floor $(DEMO)/logs/ops --world $(DEMO)/logs/day2 --route loop --noise 10 --seed 30
	$(BIN)/mosaicmap track $(DEMO)/bundles/day2.zip $(DEMO)/logs/ops --key $(DEMO)/keys/owner.key.pub --report $(DEMO)/track.json --plot $(DEMO)/track.png
	@echo "== step 9/12: simulate two runs of an omnidirectional camera through a room (~35 s)"
	$(BIN)/mosaicmap simulate omni $(DEMO)/logs/omni1 --seed 1
	$(BIN)/mosaicmap simulate omni $(DEMO)/logs/omni2 --world $(DEMO)/logs/omni1
	@echo "== step 10/12: build both runs into one map: a floor from their bird's-eye views and a route panorama (~1 min)"
	$(BIN)/mosaicmap build $(DEMO)/logs/omni1 $(DEMO)/logs/omni2 --map $(DEMO)/omni-map --workdir $(DEMO)/work-omni --config examples/omni.toml --report $(DEMO)/report-omni.json
	$(BIN)/python -m pipeline.summary $(DEMO)/report-omni.json
	@echo "== step 11/12: the route panorama as a picture, and a signed bundle of the omni map"
	$(BIN)/mosaicmap quicklook $(DEMO)/omni-map --route loop --annotate --out $(DEMO)/orp.png
	$(BIN)/mosaicmap export $(DEMO)/omni-map $(DEMO)/bundles/omni.zip --sign $(DEMO)/keys/owner.key
	@echo "== step 12/12: a night run, tracked against the omni bundle (~30 s)"
	$(BIN)/mosaicmap simulate omni $(DEMO)/logs/omni-night --world $(DEMO)/logs/omni1 --night --seed 40
	$(BIN)/mosaicmap track $(DEMO)/bundles/omni.zip $(DEMO)/logs/omni-night --key $(DEMO)/keys/owner.key.pub --report $(DEMO)/track-omni.json --plot $(DEMO)/track-omni.png
	@echo "quicklook of the latest version: $(DEMO)/quicklook.png; the diff: $(DEMO)/diff/diff.html; tracking: $(DEMO)/track.png"
	@echo "omni: the route panorama $(DEMO)/orp.png; tracking at night against it: $(DEMO)/track-omni.png"

test: install-test
	$(BIN)/python -m pytest -n 2 -q

# Maps on a real S3-compatible server (versitygw, built once into ~/.cache/mosaicmap/s3 by
# scripts/s3_server.sh: needs Go) and builds on dask worker processes; ~4 min on 2 cores.
test-integration: install-test
	bash scripts/s3_server.sh install > /dev/null
	$(BIN)/python -m pytest -m "s3 or cluster" -q

# The benchmarks behind bench/README.md's figures (a few minutes; the drone set takes most).
bench: install
	$(BIN)/python bench/bench_ingest.py
	$(BIN)/python bench/bench_register.py
	$(BIN)/python bench/bench_similarity.py
	$(BIN)/python bench/bench_optimize.py
	$(BIN)/python bench/bench_real.py
	$(BIN)/python bench/bench_loose_prior.py
	$(BIN)/python bench/bench_render.py
	$(BIN)/python bench/bench_render_large.py
	$(BIN)/python bench/bench_diff.py
	$(BIN)/python bench/bench_export.py --area2 60
	$(BIN)/python bench/bench_tracker.py
	$(BIN)/python bench/bench_tracker_speed.py
	$(BIN)/python bench/bench_reloc_index.py
	$(BIN)/python bench/bench_tracker_real.py --all
	$(BIN)/python bench/bench_omni_sim.py
	$(BIN)/python bench/bench_orp.py
	$(BIN)/python bench/bench_orp_track.py
	$(BIN)/python bench/bench_orp_build.py
	$(BIN)/python bench/bench_omni_floor.py

# ASHLAR and m2stitch beside mosaicmap on tile grids (installs the bench extra; ASHLAR
# needs a JRE); half an hour on 2 cores.
bench-peers: install
	$(BIN)/pip install -q -e '.[bench]'
	$(BIN)/python bench/bench_peers.py
	$(BIN)/python bench/bench_peers.py --real

clean:
	rm -rf $(VENV) $(DEMO) *.egg-info
