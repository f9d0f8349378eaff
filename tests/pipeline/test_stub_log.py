"""The stub executables of the pipeline-script tests log every call, also when a script runs them
side by side (``denoiser-pipeline pipeline=ablations`` trains two variants at once)."""

import subprocess

from helpers.stubs import STUB_HEADER, stub_calls


def test_stubs_run_side_by_side_log_every_call_whole(tmp_path):
    stub = tmp_path / "denoiser-train"
    stub.write_text(STUB_HEADER)
    stub.chmod(0o755)
    log = tmp_path / "calls.log"
    padding = "x" * 3000   # records longer than one small write, as a ckpt={...} dict is
    n = 64
    script = tmp_path / "side_by_side.sh"
    script.write_text("".join(f'"{stub}" seed={k} pad={padding} &\n' for k in range(n)) + "wait\n")
    subprocess.run(["bash", str(script)], check=True, env={"STUB_LOG": str(log), "PATH": "/usr/bin:/bin"})
    calls = stub_calls(log)
    assert sorted(calls) == sorted(["denoiser-train", f"seed={k}", f"pad={padding}"] for k in range(n))
