# stereo_manip: every target bootstraps first (idempotent, seconds when nothing changed).
.PHONY: bootstrap test demo bench clean

bootstrap:
	@scripts/bootstrap.sh

# (bootstraps too, after starting the Noble-pinned job in the background: scripts/make_test.sh)
test:
	@scripts/make_test.sh --durations=30

demo: bootstrap
	@scripts/run_demo.sh

bench: bootstrap
	@scripts/run_benchmarks.sh

clean:
	rm -rf build install log
