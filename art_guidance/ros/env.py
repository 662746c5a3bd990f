"""The ROS 2 environment the processes and tests run in: loopback discovery, own domain."""
from __future__ import annotations

from pathlib import Path

from art_guidance.config import default_config_dir

PROFILE_VAR = "FASTRTPS_DEFAULT_PROFILES_FILE"


def fast_discovery_profile() -> Path:
    """The packaged Fast DDS profile with faster loopback discovery."""
    return default_config_dir() / "fastdds_localhost.xml"


def isolated_ros_env(home: str | Path, domain_id: int) -> dict[str, str]:
    """Variables for processes that must talk only to each other on this machine.

    Used by the demo, the tests and the benchmarks (never by the nodes themselves, which run in
    whatever DDS set-up the user has): own domain, loopback discovery, and the packaged Fast DDS
    profile with faster discovery.

    Args:
        home: ROS_HOME for logs (created by ROS on first use).
        domain_id: ROS_DOMAIN_ID shared by the processes (0-232).
    """
    home = Path(home)
    return {"ROS_DOMAIN_ID": str(int(domain_id)), "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
            "ROS_HOME": str(home), "ROS_LOG_DIR": str(home / "log"),
            PROFILE_VAR: str(fast_discovery_profile())}
