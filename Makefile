# stereo_manip: every target bootstraps first (idempotent, seconds when nothing changed).
.PHONY: bootstrap test demo bench clean

bootstrap:
	@scripts/bootstrap.sh

test: bootstrap
	@scripts/noble_venv.sh
	@scripts/run_tests.sh --durations=30

demo: bootstrap
	@scripts/run_demo.sh

bench: bootstrap
	@scripts/run_benchmarks.sh

clean:
	rm -rf build install log
