"""Start the fall-guard daemon from a ROS 2 launch file.

    ros2 launch launch/fall_guard.launch.py config:=/etc/fall-guard/poppy_humanoid.toml namespace:=/poppy

fall-guard is a plain executable (not an ament package), so it is started
with ExecuteProcess; the namespace prefixes every relative topic it reads
and publishes (`--namespace` overrides the config's [ros].namespace).
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, ExecuteProcess, SetEnvironmentVariable
from launch.substitutions import LaunchConfiguration


def generate_launch_description():
    config = LaunchConfiguration("config")
    namespace = LaunchConfiguration("namespace")
    executable = LaunchConfiguration("executable")
    log_level = LaunchConfiguration("log_level")
    return LaunchDescription(
        [
            DeclareLaunchArgument(
                "config",
                default_value="/etc/fall-guard/poppy_humanoid.toml",
                description="fall-guard TOML config file",
            ),
            DeclareLaunchArgument(
                "namespace",
                default_value="/",
                description="ROS namespace prefixed to every topic, e.g. /poppy",
            ),
            DeclareLaunchArgument(
                "executable",
                default_value="fall-guard",
                description="path of the fall-guard binary",
            ),
            DeclareLaunchArgument(
                "log_level", default_value="info", description="RUST_LOG filter"
            ),
            SetEnvironmentVariable("RUST_LOG", log_level),
            ExecuteProcess(
                cmd=[executable, "run", "--config", config, "--namespace", namespace],
                name="fall_guard",
                output="screen",
                emulate_tty=True,
                # A crash ends the launch like a failing node would.
                respawn=False,
            ),
        ]
    )
