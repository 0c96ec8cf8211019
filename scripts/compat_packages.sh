# Sourced by bootstrap.sh and build_pkg.sh. compat_package_dirs ROOT PREFIXES prints the
# ros_compat/<pkg> folders (relative to ROOT) whose package no prefix in PREFIXES (':'-separated,
# e.g. the venv and the caller's AMENT_PREFIX_PATH) installs; this workspace's own install/ does
# not count, so a stand-in is rebuilt as long as it is needed.
compat_package_dirs() {
  local root=$1 prefixes=$2 dir pkg prefix found
  for dir in "$root"/ros_compat/*/; do
    [ -f "$dir/package.xml" ] || continue
    pkg=$(basename "$dir")
    found=0
    IFS=: read -ra _prefixes <<< "$prefixes"
    for prefix in "${_prefixes[@]}"; do
      [ -n "$prefix" ] || continue
      case "$(cd "$prefix" 2>/dev/null && pwd)" in "$root"/install*) continue ;; esac
      if [ -f "$prefix/share/$pkg/package.xml" ]; then found=1; break; fi
    done
    [ "$found" = 1 ] || printf 'ros_compat/%s\n' "$pkg"
  done
}
