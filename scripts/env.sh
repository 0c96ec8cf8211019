# Source me (bash): activates .venv and the colcon install tree of this workspace, and keeps
# ROS traffic on this machine unless the caller chose otherwise.
_sm_root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
# shellcheck disable=SC1091
. "$_sm_root/.venv/bin/activate"
export AMENT_PREFIX_PATH=${AMENT_PREFIX_PATH:+$AMENT_PREFIX_PATH:}$_sm_root/.venv
export CMAKE_PREFIX_PATH=${CMAKE_PREFIX_PATH:+$CMAKE_PREFIX_PATH:}$_sm_root/.venv
export ROS_AUTOMATIC_DISCOVERY_RANGE=${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}
# shellcheck disable=SC1091
. "$_sm_root/install/local_setup.bash"
unset _sm_root
