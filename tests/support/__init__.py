"""What the tests import as tests.support.*: helpers (paths, cli, refusals, waiting, loopback) and
doubles (hostile payloads and peers, the fuzzing harness). Doubles the benchmarks drive too are
installed modules instead: probecal.app.ursimprocess, probecal.app.headless and
probecal.core.acquisition.igtlstreamer."""
