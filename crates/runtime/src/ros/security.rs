//! DDS Security (SROS2) for the daemon's participant, configured the way rcl
//! configures it: `ROS_SECURITY_ENABLE`, `ROS_SECURITY_STRATEGY`,
//! `ROS_SECURITY_KEYSTORE` and an enclave (`[ros].enclave`, overridden by
//! `ROS_SECURITY_ENCLAVE_OVERRIDE`), whose files are the SROS2 keystore's
//! `<keystore>/enclaves/<enclave>/{identity_ca.cert.pem, cert.pem, key.pem,
//! permissions_ca.cert.pem, governance.p7s, permissions.p7s}`.
//!
//! The plugins are RustDDS's builtin ones (cargo feature `security`). What
//! happens at start is decided by [`plan`]:
//!
//! - security not enabled: an open participant, as without the feature;
//! - `Enforce`: the enclave's files must all be there and valid (each is
//!   checked here first, so that an error names the file), else the daemon
//!   refuses to start; a build without the feature refuses too;
//! - `Permissive`: as rcl, an enclave directory that does not exist (or no
//!   keystore, or a build without the feature) means an open participant,
//!   logged as a WARN; an enclave directory that exists must be complete
//!   and valid, as with `Enforce`.

use std::path::PathBuf;

use super::RosError;

/// `true` turns DDS Security on (rcl reads this variable).
pub const SECURITY_ENABLE_ENV: &str = "ROS_SECURITY_ENABLE";
/// `Enforce` or `Permissive` (the default).
pub const SECURITY_STRATEGY_ENV: &str = "ROS_SECURITY_STRATEGY";
/// The SROS2 keystore directory (holds `enclaves/`).
pub const SECURITY_KEYSTORE_ENV: &str = "ROS_SECURITY_KEYSTORE";
/// An enclave that replaces the configured one.
pub const SECURITY_ENCLAVE_OVERRIDE_ENV: &str = "ROS_SECURITY_ENCLAVE_OVERRIDE";

/// The enclave when `[ros].enclave` is not set.
pub const DEFAULT_ENCLAVE: &str = "/fall_guard";

/// Whether this binary was built with the cargo feature `security`.
pub const BUILT_IN: bool = cfg!(feature = "security");

/// The files of an enclave, in the SROS2 names RustDDS reads.
pub const ENCLAVE_FILES: [&str; 6] = [
    "identity_ca.cert.pem",
    "cert.pem",
    "key.pem",
    "permissions_ca.cert.pem",
    "governance.p7s",
    "permissions.p7s",
];

/// What rcl does when the enclave cannot be used.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Strategy {
    /// Refuse to start.
    Enforce,
    /// Run on an open participant, with a WARN.
    Permissive,
}

/// Security as the environment and the config ask for it (only present when
/// `ROS_SECURITY_ENABLE=true`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SecuritySettings {
    pub strategy: Strategy,
    /// `ROS_SECURITY_KEYSTORE`; `None` when unset or empty.
    pub keystore: Option<PathBuf>,
    /// An absolute name, `/fall_guard` or `/poppy/fall_guard`.
    pub enclave: String,
}

impl SecuritySettings {
    /// Reads the security variables through `var`; `Ok(None)` when security
    /// is not enabled. `enclave` is the configured one
    /// (`ROS_SECURITY_ENCLAVE_OVERRIDE` wins over it).
    pub fn from_vars(
        enclave: &str,
        var: impl Fn(&str) -> Option<String>,
    ) -> Result<Option<SecuritySettings>, RosError> {
        let enable = var(SECURITY_ENABLE_ENV).map(|v| v.trim().to_owned());
        match enable.as_deref() {
            None | Some("") => return Ok(None),
            Some(v) if v.eq_ignore_ascii_case("false") => return Ok(None),
            Some(v) if v.eq_ignore_ascii_case("true") => {}
            Some(v) => {
                return Err(RosError::BadSecurityVar {
                    var: SECURITY_ENABLE_ENV,
                    value: v.to_owned(),
                    expected: "true or false",
                })
            }
        }
        let strategy = match var(SECURITY_STRATEGY_ENV).map(|v| v.trim().to_owned()) {
            None => Strategy::Permissive,
            Some(v) if v.is_empty() || v.eq_ignore_ascii_case("permissive") => Strategy::Permissive,
            Some(v) if v.eq_ignore_ascii_case("enforce") => Strategy::Enforce,
            Some(v) => {
                return Err(RosError::BadSecurityVar {
                    var: SECURITY_STRATEGY_ENV,
                    value: v,
                    expected: "Enforce or Permissive",
                })
            }
        };
        let keystore = var(SECURITY_KEYSTORE_ENV)
            .map(|v| v.trim().to_owned())
            .filter(|v| !v.is_empty())
            .map(PathBuf::from);
        let enclave = match var(SECURITY_ENCLAVE_OVERRIDE_ENV).map(|v| v.trim().to_owned()) {
            Some(v) if !v.is_empty() => {
                check_enclave_name(&v).map_err(|reason| RosError::BadEnclave {
                    enclave: v.clone(),
                    from: SECURITY_ENCLAVE_OVERRIDE_ENV,
                    reason,
                })?;
                v
            }
            _ => {
                check_enclave_name(enclave).map_err(|reason| RosError::BadEnclave {
                    enclave: enclave.to_owned(),
                    from: "[ros].enclave",
                    reason,
                })?;
                enclave.to_owned()
            }
        };
        Ok(Some(SecuritySettings {
            strategy,
            keystore,
            enclave,
        }))
    }

    /// `<keystore>/enclaves/<enclave>`, when a keystore is set.
    pub fn enclave_dir(&self) -> Option<PathBuf> {
        let keystore = self.keystore.as_ref()?;
        let mut dir = keystore.join("enclaves");
        for part in self.enclave.split('/').filter(|p| !p.is_empty()) {
            dir.push(part);
        }
        Some(dir)
    }
}

/// An enclave is an absolute ROS name: `/`, or `/` followed by segments of
/// letters, digits and `_` (not starting with a digit) joined by `/`. That
/// also keeps its directory inside the keystore.
pub fn check_enclave_name(enclave: &str) -> Result<(), String> {
    if !enclave.starts_with('/') {
        return Err("expected an absolute name like \"/fall_guard\"".to_owned());
    }
    if enclave == "/" {
        return Ok(());
    }
    for part in enclave[1..].split('/') {
        let ok = !part.is_empty()
            && part.chars().all(|c| c.is_ascii_alphanumeric() || c == '_')
            && !part.starts_with(|c: char| c.is_ascii_digit());
        if !ok {
            return Err(format!(
                "segment {part:?}: expected letters, digits and _ (not starting with a digit)"
            ));
        }
    }
    Ok(())
}

/// How the participant is to be created.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Plan {
    /// No security: not enabled, or `Permissive` without a usable enclave
    /// (`why` says which, for the WARN).
    Open { why: Option<String> },
    /// The builtin plugins with the files of this enclave directory.
    Secure { strategy: Strategy, dir: PathBuf },
}

/// Decides how to create the participant, before any file is read (beyond
/// whether the enclave directory exists).
pub fn plan(security: Option<&SecuritySettings>) -> Result<Plan, RosError> {
    let Some(s) = security else {
        return Ok(Plan::Open { why: None });
    };
    let permissive = |why: String| Ok(Plan::Open { why: Some(why) });
    if !BUILT_IN {
        return match s.strategy {
            Strategy::Enforce => Err(RosError::SecurityNotBuiltIn),
            Strategy::Permissive => permissive(
                "this fall-guard was built without DDS Security (cargo feature `security`)"
                    .to_owned(),
            ),
        };
    }
    let Some(dir) = s.enclave_dir() else {
        return match s.strategy {
            Strategy::Enforce => Err(RosError::NoKeystore),
            Strategy::Permissive => permissive(format!("{SECURITY_KEYSTORE_ENV} is not set")),
        };
    };
    if !dir.is_dir() {
        return match s.strategy {
            Strategy::Enforce => Err(RosError::SecurityFile {
                path: dir,
                reason: format!(
                    "enclave {} not found in the keystore (create it, e.g. with scripts/security/sros2-keystore.sh)",
                    s.enclave
                ),
            }),
            Strategy::Permissive => permissive(format!(
                "enclave {} not found at {}",
                s.enclave,
                dir.display()
            )),
        };
    }
    Ok(Plan::Secure {
        strategy: s.strategy,
        dir,
    })
}

#[cfg(feature = "security")]
mod files {
    //! Each enclave file checked on its own, so that an error names the file
    //! and says what is wrong with it (RustDDS's own errors name neither).

    use std::path::{Path, PathBuf};

    use openssl::asn1::Asn1Time;
    use openssl::pkcs7::{Pkcs7, Pkcs7Flags};
    use openssl::pkey::{PKey, Private};
    use openssl::stack::Stack;
    use openssl::x509::store::X509StoreBuilder;
    use openssl::x509::X509;

    use super::RosError;

    fn bad(path: &Path, reason: impl Into<String>) -> RosError {
        RosError::SecurityFile {
            path: path.to_path_buf(),
            reason: reason.into(),
        }
    }

    fn read(dir: &Path, name: &str) -> Result<(PathBuf, Vec<u8>), RosError> {
        let path = dir.join(name);
        match std::fs::read(&path) {
            Ok(bytes) if bytes.is_empty() => Err(bad(&path, "empty")),
            Ok(bytes) => Ok((path, bytes)),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                Err(bad(&path, "missing from the enclave"))
            }
            Err(e) => Err(bad(&path, format!("cannot be read: {e}"))),
        }
    }

    fn certificate(dir: &Path, name: &str) -> Result<(PathBuf, X509), RosError> {
        let (path, bytes) = read(dir, name)?;
        let cert = X509::from_pem(&bytes)
            .map_err(|e| bad(&path, format!("not a PEM X.509 certificate ({e})")))?;
        in_validity(&path, &cert)?;
        Ok((path, cert))
    }

    fn in_validity(path: &Path, cert: &X509) -> Result<(), RosError> {
        let now = Asn1Time::days_from_now(0).map_err(|e| bad(path, e.to_string()))?;
        if cert.not_before() > now {
            return Err(bad(
                path,
                format!("not valid before {} (check the clock)", cert.not_before()),
            ));
        }
        if cert.not_after() < now {
            return Err(bad(path, format!("expired on {}", cert.not_after())));
        }
        Ok(())
    }

    fn private_key(dir: &Path, name: &str) -> Result<(PathBuf, PKey<Private>), RosError> {
        let (path, bytes) = read(dir, name)?;
        // RustDDS reads PKCS#8 only (`openssl genpkey` writes it).
        if !String::from_utf8_lossy(&bytes).contains("-----BEGIN PRIVATE KEY-----") {
            return Err(bad(
                &path,
                "not an unencrypted PKCS#8 PEM key (-----BEGIN PRIVATE KEY-----); convert it with `openssl pkcs8 -topk8 -nocrypt`",
            ));
        }
        let key = PKey::private_key_from_pem(&bytes).map_err(|e| {
            bad(
                &path,
                format!("not an unencrypted PEM private key ({e}); SROS2 keys carry no password"),
            )
        })?;
        Ok((path, key))
    }

    /// An S/MIME document signed by the permissions CA.
    fn signed_document(dir: &Path, name: &str, ca: &X509, ca_path: &Path) -> Result<(), RosError> {
        let (path, bytes) = read(dir, name)?;
        let (pkcs7, content) = Pkcs7::from_smime(&bytes)
            .map_err(|e| bad(&path, format!("not an S/MIME signed document ({e})")))?;
        let Some(content) = content else {
            return Err(bad(
                &path,
                "not a detached (multipart/signed) S/MIME signature: sign with `openssl smime -sign -text`",
            ));
        };
        let mut store = X509StoreBuilder::new().map_err(|e| bad(&path, e.to_string()))?;
        store
            .add_cert(ca.clone())
            .map_err(|e| bad(&path, e.to_string()))?;
        let store = store.build();
        let certs = Stack::new().map_err(|e| bad(&path, e.to_string()))?;
        let mut out = Vec::new();
        // NOVERIFY: the signer must be the permissions CA itself (checked
        // below), not a chain with S/MIME key usage; the signature is checked.
        pkcs7
            .verify(
                &certs,
                &store,
                Some(&content),
                Some(&mut out),
                Pkcs7Flags::NOVERIFY,
            )
            .map_err(|e| {
                bad(
                    &path,
                    format!("signature does not verify ({e}); sign it with the permissions CA"),
                )
            })?;
        let signers = pkcs7.signers(&certs, Pkcs7Flags::empty()).map_err(|e| {
            bad(
                &path,
                format!("no signer certificate in the signature ({e})"),
            )
        })?;
        let ca_der = ca.to_der().map_err(|e| bad(&path, e.to_string()))?;
        let by_ca = signers
            .iter()
            .any(|s| s.to_der().is_ok_and(|der| der == ca_der));
        if !by_ca {
            return Err(bad(
                &path,
                format!("not signed by the permissions CA {}", ca_path.display()),
            ));
        }
        Ok(())
    }

    /// Every file of the enclave in `dir`: present, parseable, the identity
    /// certificate issued by the identity CA and matching the private key,
    /// the two documents signed by the permissions CA.
    pub fn check(dir: &Path) -> Result<(), RosError> {
        let (ca_path, identity_ca) = certificate(dir, "identity_ca.cert.pem")?;
        let (cert_path, cert) = certificate(dir, "cert.pem")?;
        let ca_key = identity_ca
            .public_key()
            .map_err(|e| bad(&ca_path, format!("no public key ({e})")))?;
        if !cert.verify(&ca_key).unwrap_or(false) {
            return Err(bad(
                &cert_path,
                format!("not issued by the identity CA {}", ca_path.display()),
            ));
        }
        let (key_path, key) = private_key(dir, "key.pem")?;
        let cert_key = cert
            .public_key()
            .map_err(|e| bad(&cert_path, format!("no public key ({e})")))?;
        if !cert_key.public_eq(&key) {
            return Err(bad(
                &key_path,
                format!("not the private key of {}", cert_path.display()),
            ));
        }
        let (perm_ca_path, permissions_ca) = certificate(dir, "permissions_ca.cert.pem")?;
        signed_document(dir, "governance.p7s", &permissions_ca, &perm_ca_path)?;
        signed_document(dir, "permissions.p7s", &permissions_ca, &perm_ca_path)?;
        Ok(())
    }
}

/// Checks every file of the enclave in `dir` (see [`files::check`]); an
/// error names the file and what is wrong with it.
#[cfg(feature = "security")]
pub fn check_enclave_files(dir: &std::path::Path) -> Result<(), RosError> {
    files::check(dir)
}

/// The builder with the builtin security plugins of `plan`, or as it was.
pub(super) fn configure(
    builder: rustdds::DomainParticipantBuilder,
    plan: &Plan,
) -> Result<rustdds::DomainParticipantBuilder, RosError> {
    match plan {
        Plan::Open { why: None } => Ok(builder),
        Plan::Open { why: Some(why) } => {
            tracing::warn!(
                "{SECURITY_ENABLE_ENV}=true but DDS Security is off ({SECURITY_STRATEGY_ENV}=Permissive): {why}; the participant is open"
            );
            Ok(builder)
        }
        #[cfg(feature = "security")]
        Plan::Secure { dir, .. } => {
            check_enclave_files(dir)?;
            let files = rustdds::DomainParticipantSecurityConfigFiles::with_ros_default_names(
                dir,
                String::new(),
            );
            Ok(builder.builtin_security(files))
        }
        #[cfg(not(feature = "security"))]
        Plan::Secure { .. } => Err(RosError::SecurityNotBuiltIn),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    #[cfg(not(feature = "security"))]
    use std::path::Path;

    use crate::ros::tests::env;

    #[test]
    fn off_unless_enabled() {
        assert_eq!(
            SecuritySettings::from_vars(DEFAULT_ENCLAVE, env(&[])).unwrap(),
            None
        );
        for v in ["", "false", "FALSE"] {
            let s = SecuritySettings::from_vars(DEFAULT_ENCLAVE, env(&[(SECURITY_ENABLE_ENV, v)]));
            assert_eq!(s.unwrap(), None, "{v:?}");
        }
        assert_eq!(plan(None).unwrap(), Plan::Open { why: None });
    }

    #[test]
    fn reads_the_rcl_variables() {
        let s = SecuritySettings::from_vars(
            "/fall_guard",
            env(&[
                (SECURITY_ENABLE_ENV, "true"),
                (SECURITY_STRATEGY_ENV, "Enforce"),
                (SECURITY_KEYSTORE_ENV, "/etc/keystore"),
            ]),
        )
        .unwrap()
        .unwrap();
        assert_eq!(s.strategy, Strategy::Enforce);
        assert_eq!(
            s.enclave_dir(),
            Some(PathBuf::from("/etc/keystore/enclaves/fall_guard"))
        );
        let s = SecuritySettings::from_vars(
            "/fall_guard",
            env(&[
                (SECURITY_ENABLE_ENV, "true"),
                (SECURITY_ENCLAVE_OVERRIDE_ENV, "/poppy/fall_guard"),
                (SECURITY_KEYSTORE_ENV, "ks"),
            ]),
        )
        .unwrap()
        .unwrap();
        assert_eq!(s.strategy, Strategy::Permissive);
        assert_eq!(s.enclave, "/poppy/fall_guard");
        assert_eq!(
            s.enclave_dir(),
            Some(PathBuf::from("ks/enclaves/poppy/fall_guard"))
        );
    }

    #[test]
    fn bad_values_name_the_variable_or_key() {
        let e = SecuritySettings::from_vars(DEFAULT_ENCLAVE, env(&[(SECURITY_ENABLE_ENV, "1")]))
            .expect_err("1 is not true");
        assert!(e.to_string().contains("ROS_SECURITY_ENABLE"), "{e}");
        let e = SecuritySettings::from_vars(
            DEFAULT_ENCLAVE,
            env(&[
                (SECURITY_ENABLE_ENV, "true"),
                (SECURITY_STRATEGY_ENV, "Strict"),
            ]),
        )
        .expect_err("not a strategy");
        assert!(e.to_string().contains("ROS_SECURITY_STRATEGY"), "{e}");
        for bad in ["fall_guard", "/../etc", "/a//b", "/1x", "/a/"] {
            let e = SecuritySettings::from_vars(bad, env(&[(SECURITY_ENABLE_ENV, "true")]))
                .expect_err(bad);
            assert!(e.to_string().contains("[ros].enclave"), "{e}");
        }
        let e = SecuritySettings::from_vars(
            DEFAULT_ENCLAVE,
            env(&[
                (SECURITY_ENABLE_ENV, "true"),
                (SECURITY_ENCLAVE_OVERRIDE_ENV, "../x"),
            ]),
        )
        .expect_err("bad override");
        assert!(
            e.to_string().contains("ROS_SECURITY_ENCLAVE_OVERRIDE"),
            "{e}"
        );
    }

    #[cfg(not(feature = "security"))]
    fn enabled(strategy: Strategy, keystore: Option<&Path>) -> SecuritySettings {
        SecuritySettings {
            strategy,
            keystore: keystore.map(Path::to_path_buf),
            enclave: DEFAULT_ENCLAVE.to_owned(),
        }
    }

    /// Without the feature, Enforce refuses and Permissive runs open (with
    /// the reason for its WARN).
    #[cfg(not(feature = "security"))]
    #[test]
    fn without_the_feature_enforce_refuses_to_start() {
        let dir = tempfile::tempdir().unwrap();
        let e = plan(Some(&enabled(Strategy::Enforce, Some(dir.path())))).expect_err("refuse");
        assert!(matches!(e, RosError::SecurityNotBuiltIn));
        let text = e.to_string();
        assert!(
            text.contains("--features security") && text.contains("Enforce"),
            "{text}"
        );
        let p = plan(Some(&enabled(Strategy::Permissive, Some(dir.path())))).unwrap();
        assert!(matches!(p, Plan::Open { why: Some(w) } if w.contains("without DDS Security")));
    }
}
