# Source this file to use the built workspace: `source scripts/env.sh`.
# It puts the project venv (the ROS 2 Jazzy prefix) and the colcon install space on the paths.
_SPH_ROOT="$(cd "$(dirname "${BASH_SOURCE[0]:-$0}")/.." && pwd)"
export VIRTUAL_ENV="${SPH_VENV:-$_SPH_ROOT/.venv}"
export PATH="$VIRTUAL_ENV/bin:$PATH"
export AMENT_PREFIX_PATH="$VIRTUAL_ENV${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}"
export LD_LIBRARY_PATH="$VIRTUAL_ENV/lib${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
export RMW_IMPLEMENTATION="${RMW_IMPLEMENTATION:-rmw_fastrtps_cpp}"
# UDP, not Fast DDS's shared memory: with shared memory a killed peer can block a publish (and the
# driver's servo loop with it) for seconds (see src/tissue_common/tissue_common/transport.py).
export FASTDDS_BUILTIN_TRANSPORTS="${FASTDDS_BUILTIN_TRANSPORTS:-UDPv4}"
if [[ -f "$_SPH_ROOT/install/setup.sh" ]]; then
  # colcon's setup scripts read unset variables; tolerate them even under `set -u`.
  case $- in *u*) _SPH_NOUNSET=1; set +u ;; *) _SPH_NOUNSET=0 ;; esac
  COLCON_CURRENT_PREFIX="$_SPH_ROOT/install" . "$_SPH_ROOT/install/setup.sh"
  [[ $_SPH_NOUNSET == 1 ]] && set -u
  unset _SPH_NOUNSET
fi
unset _SPH_ROOT
