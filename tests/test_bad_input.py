"""Files a user meets at the edges: a sweep file that is not one (or is damaged) is a named
`ValueError`, and a write killed half-way leaves the previous file whole.  (The command
line's usage errors are catalogued in tests/test_cli.py, the data files' in
test_fit_helix_data.py and test_tweezer_data.py.)"""

import subprocess
import sys
import textwrap
import zipfile

import numpy as np
import pytest

import helixrod as hr


@pytest.fixture
def sweep_file(tmp_path):
    path = tmp_path / "sweep.npz"
    hr.save_sweep(path, hr.sweep(hr.Rod(1.0, 1.5, 0.8), np.linspace(0.2, 1.0, 3), np.linspace(-1.0, 1.0, 4), fields=("count",)))
    return path


def test_load_sweep_names_what_is_wrong(tmp_path, sweep_file):
    garbage = tmp_path / "garbage.npz"
    garbage.write_bytes(b"not an archive")
    other = tmp_path / "other.npz"
    np.savez(other, a=np.ones(3))
    single = tmp_path / "single.npy"
    np.save(single, np.ones(3))
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(sweep_file.read_bytes()[:200])
    cases = [
        (garbage, "not a NumPy .npz archive"),
        (other, "no readable 'meta' entry"),
        (single, "a single array, not an archive"),
        (truncated, "is not a helixrod sweep file"),
    ]
    for path, fragment in cases:
        with pytest.raises(ValueError, match=fragment):
            hr.load_sweep(path)
    with pytest.raises(FileNotFoundError):
        hr.load_sweep(tmp_path / "missing.npz")
    assert hr.load_sweep(sweep_file)["count"].shape == (3, 4)
    assert zipfile.is_zipfile(sweep_file)


def test_a_write_killed_half_way_leaves_the_old_file_whole(tmp_path, sweep_file):
    """A process killed (SIGKILL) in the middle of `save_sweep` over an existing file: the
    previous file still loads, unchanged."""
    before = sweep_file.read_bytes()
    script = textwrap.dedent(
        f"""
        import os, signal
        import numpy as np
        import helixrod as hr

        result = hr.load_sweep({str(sweep_file)!r})

        def dying(file, **arrays):  # half a zip archive, then the process dies
            file.write(b"PK\\x03\\x04" + b"x" * 4096)
            file.flush()
            os.kill(os.getpid(), signal.SIGKILL)

        np.savez = dying
        hr.save_sweep({str(sweep_file)!r}, result)
        """
    )
    process = subprocess.run([sys.executable, "-c", script], capture_output=True, timeout=300)
    assert process.returncode == -9, process.stderr.decode()
    assert sweep_file.read_bytes() == before
    assert hr.load_sweep(sweep_file)["count"].shape == (3, 4)
