# Sourced, not run: defines debian_mirror, which prints the Debian archive this machine's own apt
# uses, so that no script here names an archive host. Used by xr-root.sh (the trixie root for the
# Monado test) and made available by setup.sh.
#
#   $CAO_XR_DEBIAN_MIRROR, when set, wins as it is.
#   Else the first Debian archive entry (not the security archive) of, in this order:
#     /etc/apt/sources.list.d/*.sources  deb822 stanzas: Types holds "deb", Suites holds a Debian
#                                        release name (the machine's codename, stable, sid, ...),
#                                        Enabled is not "no"; its first URIs value is taken;
#     /etc/apt/sources.list              one-line entries "deb [options] URI SUITE COMPONENTS...";
#     /etc/apt/sources.list.d/*.list     the same, in the one-line format.
#   Entries for suites such as bookworm-security, bookworm-updates or a vendor's own (nodistro,
#   cloud-sdk-bookworm) are skipped, and so is any URI naming "security".
# $CAO_XR_APT_ETC (default /etc/apt) moves the directory looked at (for tests).
# Prints the URI on stdout and returns 0, or names the files looked at on stderr and returns 1.

debian_mirror() {
  if [ -n "${CAO_XR_DEBIAN_MIRROR:-}" ]; then
    printf '%s\n' "$CAO_XR_DEBIAN_MIRROR"
    return 0
  fi
  local etc="${CAO_XR_APT_ETC:-/etc/apt}"
  # Debian's release names and aliases; the machine's own codename joins them on Debian.
  local suites="oldoldstable oldstable stable testing unstable sid buster bullseye bookworm trixie forky duke"
  local id="" codename=""
  if [ -r /etc/os-release ]; then
    id=$(. /etc/os-release && printf '%s' "${ID:-}")
    codename=$(. /etc/os-release && printf '%s' "${VERSION_CODENAME:-}")
  fi
  case " $suites " in
    *" $codename "*) ;;
    *) if [ "$id" = debian ] && [ -n "$codename" ]; then suites="$codename $suites"; fi ;;
  esac

  local f uri looked=()
  for f in "$etc"/sources.list.d/*.sources; do
    [ -f "$f" ] || continue
    looked+=("$f")
    uri=$(awk -v suites="$suites" '
      BEGIN { n = split(suites, s, " "); for (i = 1; i <= n; i++) ok[s[i]] = 1 }
      function field_end() { if (name != "") val[name] = val[name] " " cur; name = "" }
      function stanza_end(   k, t, u, m, nt, nu, ns, deb, suite) {
        field_end()
        nt = split(val["types"], t, " "); nu = split(val["uris"], u, " ")
        ns = split(val["suites"], m, " ")
        deb = 0; for (k = 1; k <= nt; k++) if (t[k] == "deb") deb = 1
        suite = 0; for (k = 1; k <= ns; k++) if (m[k] in ok) suite = 1
        if (deb && suite && nu > 0 && tolower(val["enabled"]) !~ /no/ && u[1] !~ /security/) {
          print u[1]; found = 1; exit
        }
        delete val
      }
      /^[ \t]*#/ { next }
      /^[ \t]*$/ { stanza_end(); next }
      /^[ \t]/   { cur = cur " " $0; next }                 # continuation of a field
      {
        field_end()
        p = index($0, ":"); if (p == 0) next
        name = tolower(substr($0, 1, p - 1)); cur = substr($0, p + 1)
      }
      END { if (!found) stanza_end() }
    ' "$f")
    if [ -n "$uri" ]; then printf '%s\n' "${uri%/}"; return 0; fi
  done
  local lists=()
  if [ -f "$etc/sources.list" ]; then lists+=("$etc/sources.list"); fi
  for f in "$etc"/sources.list.d/*.list; do
    if [ -f "$f" ]; then lists+=("$f"); fi
  done
  for f in "${lists[@]}"; do
    looked+=("$f")
    uri=$(awk -v suites="$suites" '
      BEGIN { n = split(suites, s, " "); for (i = 1; i <= n; i++) ok[s[i]] = 1 }
      /^[ \t]*#/ { next }
      {
        line = $0; sub(/#.*/, "", line); gsub(/\[[^]]*\]/, " ", line)   # comments, [options]
        k = split(line, w, " ")
        if (k >= 3 && w[1] == "deb" && (w[3] in ok) && w[2] !~ /security/) { print w[2]; exit }
      }
    ' "$f")
    if [ -n "$uri" ]; then printf '%s\n' "${uri%/}"; return 0; fi
  done
  {
    echo "no Debian archive found in this machine's apt sources: no 'deb' entry for a Debian release"
    echo "  (one of: $suites) outside the security archive in"
    if [ ${#looked[@]} -gt 0 ]; then
      printf '    %s\n' "${looked[@]}"
    else
      echo "    $etc/sources.list.d/*.sources, $etc/sources.list, $etc/sources.list.d/*.list (none exist)"
    fi
    echo "  Set CAO_XR_DEBIAN_MIRROR to the URL of a Debian mirror."
  } >&2
  return 1
}
