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


def test_every_node_parameter_and_progress_key_is_documented() -> None:
    """Each parameter the nodes declare (per-sensor ones as <name>.x) is named in docs/interfaces.md
    and, but for the per-sensor calibration, in README.md; so are the new topics and progress keys."""
    import rclpy
    from rclpy.context import Context

    from magcal_ros.app.ros_driver import pick_domain_id, release_domain_id
    from magcal_ros.nodes.calibration_node import CalibrationNode
    from magcal_ros.nodes.correction_node import CorrectionNode

    readme = (ROOT / "README.md").read_text()
    interfaces = (ROOT / "docs" / "interfaces.md").read_text()
    context = Context()
    domain = pick_domain_id()  # never the environment's ROS_DOMAIN_ID (a vehicle's live domain)
    rclpy.init(context=context, args=["--ros-args", "-p", "uncorrected_sensors:=[mag1, mag2, mag3, mag4]"],
               domain_id=domain)
    names: set[str] = set()
    try:
        for make in (CorrectionNode, CalibrationNode):
            node = make(context=context)
            names |= {n.replace("mag1.", "<name>.") for n in node.list_parameters([], 0).names
                      if not n.startswith(("mag2.", "mag3.", "mag4.")) and n not in ("use_sim_time", "start_type_description_service")}
            node.close() if hasattr(node, "close") else None
            node.destroy_node()
    finally:
        rclpy.shutdown(context=context)
        release_domain_id(domain)
    assert {"prior", "site", "date", "max_residual", "assess_period", "interference_topics", "<name>.interference"} <= names
    assert [n for n in sorted(names) if f"`{n}`" not in interfaces] == []
    assert [n for n in sorted(names) if not n.startswith("<name>.") and n not in readme] == []
    for key in ("baseline_gradient", "stale_current", "envelope_pitch_deg", "advice", "undetermined", "assessed"):
        assert key in readme and key in interfaces, key
