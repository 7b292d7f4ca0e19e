"""The README stands alone and documents the node interfaces users rely on."""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_readme_points_only_into_the_repository() -> None:
    readme = (ROOT / "README.md").read_text()
    assert "../shared" not in readme and "/work/shared" not in readme
    assert "docs/interfaces.md" in readme and (ROOT / "docs" / "interfaces.md").is_file()


def test_user_visible_names_are_documented_in_readme_and_interfaces() -> None:
    readme = (ROOT / "README.md").read_text()
    interfaces = (ROOT / "docs" / "interfaces.md").read_text()
    for name in ("gradient_stamped", "/diagnostics", "uncorrected_sensors", "covariance", "sensor_timeout",
                 "output_timeout", "max_drop_fraction", "backups", ".bak", "use_sim_time"):
        assert name in readme, name
    for name in ("gradient_stamped", "/diagnostics", "uncorrected_sensors", "<name>.covariance", "sensor_timeout",
                 "output_timeout", "max_drop_fraction", "backups", "<name>.lost", "sync_window_ms"):
        assert name in interfaces, name
