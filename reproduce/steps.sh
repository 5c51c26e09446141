# Sourced by the recipes that run several commands: `step CMD ARGS...` runs one step so that
# Ctrl-C or SIGTERM sent to the recipe reaches the step under way (a fit ends its MLflow run
# KILLED) and ends the recipe with 130 (SIGINT) or 143 (SIGTERM), no further step started.
# Bash runs a foreground command to its end before its traps; a step in the background is
# waited for, and `wait` returns as soon as a trapped signal arrives. Background commands of a
# script ignore SIGINT, so the step is sent SIGTERM, which fgat treats as a stop as well.
_step_pid=
_stop_recipe() {
    trap - INT TERM
    if [ -n "$_step_pid" ]; then
        kill -TERM "$_step_pid" 2>/dev/null || true
        wait "$_step_pid" 2>/dev/null || true
    fi
    exit "$1"
}
trap '_stop_recipe 130' INT
trap '_stop_recipe 143' TERM
step() {
    "$@" &
    _step_pid=$!
    local code=0
    wait "$_step_pid" || code=$?
    _step_pid=
    return "$code"
}
