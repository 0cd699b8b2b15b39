#!/usr/bin/env bash
# An SROS2 keystore made with plain openssl (no ROS installation, no sros2
# tool), in the layout rcl and fall-guard read (docs/ros.md, "Security"):
#
#   KEYSTORE/public/{identity_ca,permissions_ca}.cert.pem
#   KEYSTORE/private/{identity_ca,permissions_ca}.key.pem
#   KEYSTORE/enclaves/governance.{xml,p7s}
#   KEYSTORE/enclaves/<enclave>/{identity_ca.cert.pem, permissions_ca.cert.pem,
#       governance.p7s, cert.pem, key.pem, permissions.xml, permissions.p7s}
#
# Two CAs (EC P-256, SHA-256): the identity CA issues each enclave's
# certificate (subject CN=<enclave>), the permissions CA signs the governance
# and each enclave's permissions (S/MIME, as `openssl smime -sign -text`).
# The governance protects everything: no unauthenticated participant, join
# access control, discovery and liveliness encrypted, RTPS messages signed,
# and on every topic read and write access control with each DATA
# submessage encrypted whole, payload included (metadata_protection_kind
# ENCRYPT). The payload's own, end-to-end transform (data_protection_kind)
# is NONE by default: RustDDS 0.15 fails to decode it for a payload whose
# length is not a multiple of 4 (the AES-GCM tag check fails at the reader,
# and the reliable stream stalls there), which /diagnostics messages are. The permissions grant each enclave what it names and DENY the
# rest; ROS topic names are mapped to their DDS names (/x/y -> rt/x/y), and
# every enclave may also use the ROS 2 plumbing a node needs (publish
# rt/rosout, rt/parameter_events, ros_discovery_info and the replies of its
# own parameter services rr/<enclave>/*; subscribe rt/parameter_events,
# rt/clock, ros_discovery_info and its requests rq/<enclave>/*: the enclave
# is the node's full name, as sros2 has it).
#
# Usage:
#   scripts/security/sros2-keystore.sh init KEYSTORE [--domains MIN-MAX] [--data-protection NONE|SIGN|ENCRYPT]
#       the CAs and the governance (kept when present; default domains 0-232,
#       data protection NONE: see below)
#   scripts/security/sros2-keystore.sh enclave KEYSTORE ENCLAVE [--publish T,...] [--subscribe T,...] [--domains MIN-MAX]
#       one enclave (an absolute name, /fall_guard) granted those ROS topics
#   scripts/security/sros2-keystore.sh fall-guard KEYSTORE [--namespace /NS] [--domains MIN-MAX]
#       init, then the daemon's enclave and two peers' (topics of docs/ros.md
#       under the namespace):
#         <NS>/fall_guard          the daemon: publishes its outputs and
#                                  /joint_states, subscribes to its inputs
#         <NS>/fall_guard_monitor  a safety node: subscribes to the outputs
#         <NS>/fall_guard_driver   the robot side: publishes /joint_states,
#                                  /planned_trajectory and the camera
#
# Then: ROS_SECURITY_ENABLE=true ROS_SECURITY_STRATEGY=Enforce
# ROS_SECURITY_KEYSTORE=KEYSTORE fall-guard run ... (enclave: [ros].enclave).
# Keep private/ off the robot: only enclaves/<its enclave>/ is needed there.
set -euo pipefail

usage() { sed -n '/^# Usage:/,/^# Then:/p' "$0" | sed 's/^# \{0,1\}//' >&2; exit 2; }
die() { echo "sros2-keystore.sh: $*" >&2; exit 1; }

command -v openssl >/dev/null || die "openssl not found (apt install openssl)"
[ $# -ge 2 ] || usage
cmd=$1 keystore=$2
shift 2

domains="0-232"
data_protection="NONE"
valid_days=3650

# ROS topic name -> DDS topic name ("/a/b" -> "rt/a/b"); DDS names pass.
dds_topic() {
  case "$1" in
    rt/*|rq/*|rr/*|ros_discovery_info) printf '%s' "$1" ;;
    /*) printf 'rt%s' "$1" ;;
    *) die "topic '$1': give an absolute ROS name (/joint_states) or a DDS name (rt/...)" ;;
  esac
}

check_enclave_name() {
  [[ "$1" =~ ^(/[A-Za-z_][A-Za-z0-9_]*)+$ ]] ||
    die "enclave '$1': expected an absolute name like /fall_guard (segments of letters, digits, _)"
}

domain_xml() {
  local min=${domains%-*} max=${domains#*-}
  [[ "$min" =~ ^[0-9]+$ && "$max" =~ ^[0-9]+$ && $min -le $max ]] ||
    die "--domains '$domains': expected MIN-MAX, e.g. 0-232"
  printf '<domains><id_range><min>%s</min><max>%s</max></id_range></domains>' "$min" "$max"
}

# Self-signed CA: $1 = name (identity_ca, permissions_ca).
make_ca() {
  local name=$1
  local key="$keystore/private/$name.key.pem" cert="$keystore/public/$name.cert.pem"
  [ -f "$key" ] && [ -f "$cert" ] && return 0
  openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$key" 2>/dev/null
  chmod 600 "$key"
  openssl req -x509 -new -key "$key" -sha256 -days "$valid_days" -out "$cert" \
    -config <(printf '[req]\nprompt=no\ndistinguished_name=dn\nx509_extensions=ext\n[dn]\nCN=sros2 %s\n[ext]\nbasicConstraints=critical,CA:true\nkeyUsage=critical,keyCertSign,cRLSign,digitalSignature\nsubjectKeyIdentifier=hash\n' "${name/_/ }")
}

# S/MIME signature by the permissions CA: $1 = in.xml, $2 = out.p7s.
sign() {
  openssl smime -sign -text -in "$1" -out "$2" \
    -signer "$keystore/public/permissions_ca.cert.pem" \
    -inkey "$keystore/private/permissions_ca.key.pem"
}

cmd_init() {
  mkdir -p "$keystore/public" "$keystore/private" "$keystore/enclaves"
  chmod 700 "$keystore/private"
  make_ca identity_ca
  make_ca permissions_ca
  local gov="$keystore/enclaves/governance.xml"
  if [ ! -f "$keystore/enclaves/governance.p7s" ]; then
    cat > "$gov" <<EOF
<?xml version="1.0" encoding="UTF-8"?>
<dds xmlns:xsi="http://www.w3.org/2001/XMLSchema-instance" xsi:noNamespaceSchemaLocation="http://www.omg.org/spec/DDS-SECURITY/20170901/omg_shared_ca_governance.xsd">
  <domain_access_rules>
    <domain_rule>
      $(domain_xml)
      <allow_unauthenticated_participants>false</allow_unauthenticated_participants>
      <enable_join_access_control>true</enable_join_access_control>
      <discovery_protection_kind>ENCRYPT</discovery_protection_kind>
      <liveliness_protection_kind>ENCRYPT</liveliness_protection_kind>
      <rtps_protection_kind>SIGN</rtps_protection_kind>
      <topic_access_rules>
        <topic_rule>
          <topic_expression>*</topic_expression>
          <enable_discovery_protection>true</enable_discovery_protection>
          <enable_liveliness_protection>true</enable_liveliness_protection>
          <enable_read_access_control>true</enable_read_access_control>
          <enable_write_access_control>true</enable_write_access_control>
          <metadata_protection_kind>ENCRYPT</metadata_protection_kind>
          <data_protection_kind>${data_protection}</data_protection_kind>
        </topic_rule>
      </topic_access_rules>
    </domain_rule>
  </domain_access_rules>
</dds>
EOF
    sign "$gov" "$keystore/enclaves/governance.p7s"
  fi
}

# $1 = enclave, $2 = comma-separated ROS topics to publish, $3 = to subscribe.
cmd_enclave() {
  local enclave=$1 publish=$2 subscribe=$3
  check_enclave_name "$enclave"
  [ -f "$keystore/enclaves/governance.p7s" ] || die "$keystore is not a keystore: run '$0 init $keystore' first"
  local dir="$keystore/enclaves${enclave}"
  mkdir -p "$dir"
  cp "$keystore/public/identity_ca.cert.pem" "$keystore/public/permissions_ca.cert.pem" \
    "$keystore/enclaves/governance.p7s" "$dir/"

  # Identity: a key and a certificate CN=<enclave> from the identity CA.
  openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$dir/key.pem" 2>/dev/null
  chmod 600 "$dir/key.pem"
  local subj_conf
  subj_conf=$(printf '[req]\nprompt=no\ndistinguished_name=dn\n[dn]\nCN=%s\n' "$enclave")
  openssl req -new -key "$dir/key.pem" -sha256 -out "$dir/req.csr" -config <(printf '%s\n' "$subj_conf")
  openssl x509 -req -in "$dir/req.csr" -sha256 -days "$valid_days" \
    -CA "$keystore/public/identity_ca.cert.pem" -CAkey "$keystore/private/identity_ca.key.pem" \
    -set_serial "0x$(openssl rand -hex 8)" -out "$dir/cert.pem" \
    -extfile <(printf 'basicConstraints=CA:false\nkeyUsage=critical,digitalSignature,keyAgreement\n') 2>/dev/null
  rm -f "$dir/req.csr"

  # Permissions: the topics given, the ROS 2 plumbing, nothing else.
  local pub_xml="" sub_xml="" t
  local IFS=,
  for t in $publish; do [ -n "$t" ] && pub_xml+="<topic>$(dds_topic "$t")</topic>"; done
  for t in $subscribe; do [ -n "$t" ] && sub_xml+="<topic>$(dds_topic "$t")</topic>"; done
  unset IFS
  local node="${enclave#/}"
  local not_before not_after
  not_before=$(date -u -d '-1 day' +%Y-%m-%dT%H:%M:%S)
  not_after=$(date -u -d "+$valid_days days" +%Y-%m-%dT%H:%M:%S)
  cat > "$dir/permissions.xml" <<EOF
<?xml version="1.0" encoding="UTF-8"?>
<dds xmlns:xsi="http://www.w3.org/2001/XMLSchema-instance" xsi:noNamespaceSchemaLocation="http://www.omg.org/spec/DDS-Security/20170901/omg_shared_ca_permissions.xsd">
  <permissions>
    <grant name="$enclave">
      <subject_name>CN=$enclave</subject_name>
      <validity>
        <not_before>$not_before</not_before>
        <not_after>$not_after</not_after>
      </validity>
      <allow_rule>
        $(domain_xml)
        <publish>
          <topics>${pub_xml}<topic>rt/rosout</topic><topic>rt/parameter_events</topic><topic>ros_discovery_info</topic><topic>rr/${node}/*</topic></topics>
        </publish>
        <subscribe>
          <topics>${sub_xml}<topic>rt/parameter_events</topic><topic>rt/clock</topic><topic>ros_discovery_info</topic><topic>rq/${node}/*</topic></topics>
        </subscribe>
      </allow_rule>
      <default>DENY</default>
    </grant>
  </permissions>
</dds>
EOF
  sign "$dir/permissions.xml" "$dir/permissions.p7s"
  echo "enclave $enclave: $dir"
}

case "$cmd" in
  init)
    while [ $# -gt 0 ]; do
      case "$1" in
        --domains) domains=$2; shift 2 ;;
        --data-protection) data_protection=$2; shift 2 ;;
        *) usage ;;
      esac
    done
    case "$data_protection" in NONE|SIGN|ENCRYPT) ;; *) die "--data-protection: NONE, SIGN or ENCRYPT" ;; esac
    cmd_init
    echo "keystore: $keystore"
    ;;
  enclave)
    [ $# -ge 1 ] || usage
    enclave=$1; shift
    publish="" subscribe=""
    while [ $# -gt 0 ]; do
      case "$1" in
        --publish) publish=$2; shift 2 ;;
        --subscribe) subscribe=$2; shift 2 ;;
        --domains) domains=$2; shift 2 ;;
        *) usage ;;
      esac
    done
    cmd_enclave "$enclave" "$publish" "$subscribe"
    ;;
  fall-guard)
    ns=""
    while [ $# -gt 0 ]; do
      case "$1" in
        --namespace) ns=${2%/}; shift 2 ;;
        --domains) domains=$2; shift 2 ;;
        *) usage ;;
      esac
    done
    [ -z "$ns" ] || check_enclave_name "$ns"
    cmd_init
    outputs="$ns/fall_guard/forecast,$ns/fall_guard/horizons_ms,$ns/fall_guard/fall_imminent,/diagnostics"
    inputs="$ns/joint_states,$ns/planned_trajectory,$ns/head_camera/image_raw/compressed"
    cmd_enclave "$ns/fall_guard" "$outputs,$ns/joint_states" "$inputs"
    cmd_enclave "$ns/fall_guard_monitor" "" "$outputs,$ns/joint_states"
    cmd_enclave "$ns/fall_guard_driver" "$inputs" ""
    ;;
  *) usage ;;
esac
