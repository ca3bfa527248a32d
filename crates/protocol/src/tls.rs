//! TLS on every link (rustls with ring), so that nobody on the path can
//! read or alter rays, geometry, tiles or results.
//!
//! A farm shares one certificate authority: every daemon has a certificate
//! and key it presents when it accepts (the scheduler to workers and
//! clients, a worker to its peers), and every node that connects verifies
//! the other end against the authority's certificate. The simplest farm
//! uses one self-signed certificate everywhere ([`generate`], `locus
//! tls-init`): it is then its own authority. Nodes are dialled by address
//! (an IP, a container or pod name), so the certificate is checked for one
//! fixed server name, [`SERVER_NAME`] unless the files say another, not for
//! the address. TLS comes on top of the token handshake, which still
//! proves that both ends hold the cluster token.

use crate::error::ProtocolError;
use crate::stream::Stream;
use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, PrivateKeyDer, ServerName};
use serde::{Deserialize, Serialize};
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use tokio::net::TcpStream;
use tokio_rustls::{TlsAcceptor, TlsConnector};

/// The name certificates are issued for and checked against, unless the
/// configuration names another.
pub const SERVER_NAME: &str = "locus";

/// Where a node's TLS material is: flags or the config file's `[tls]`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TlsFiles {
    /// This node's certificate chain (PEM), presented when it accepts.
    pub cert: Option<PathBuf>,
    /// Its private key (PEM).
    pub key: Option<PathBuf>,
    /// The authority that signed every node's certificate (PEM); the
    /// node's own certificate when not given (one self-signed certificate
    /// for the whole farm).
    pub ca: Option<PathBuf>,
    /// The name certificates are checked for ([`SERVER_NAME`] when not
    /// given).
    pub server_name: Option<String>,
}

impl TlsFiles {
    /// Whether any TLS setting is given: then TLS is on.
    pub fn is_set(&self) -> bool {
        self.cert.is_some() || self.key.is_some() || self.ca.is_some()
    }

    /// The settings of `self`, each overridden by `over`'s where given.
    pub fn overridden_by(&self, over: &TlsFiles) -> TlsFiles {
        TlsFiles {
            cert: over.cert.clone().or_else(|| self.cert.clone()),
            key: over.key.clone().or_else(|| self.key.clone()),
            ca: over.ca.clone().or_else(|| self.ca.clone()),
            server_name: over
                .server_name
                .clone()
                .or_else(|| self.server_name.clone()),
        }
    }
}

/// A node's TLS: what it presents when accepting (if it has a key), and
/// what it trusts when connecting. Cheap to clone.
#[derive(Clone)]
pub struct Tls {
    acceptor: Option<TlsAcceptor>,
    connector: TlsConnector,
    name: ServerName<'static>,
}

impl std::fmt::Debug for Tls {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Tls")
            .field("accepts", &self.acceptor.is_some())
            .field("name", &self.name)
            .finish()
    }
}

/// TLS settings that cannot be used: a file, named, or the settings as
/// a whole.
#[derive(Debug, thiserror::Error)]
pub enum TlsFileError {
    #[error("TLS: {what} {}: {why}", path.display())]
    File {
        what: &'static str,
        path: PathBuf,
        why: String,
    },
    #[error("TLS: {0}")]
    Settings(String),
}

fn file_err(what: &'static str, path: &Path, why: impl ToString) -> TlsFileError {
    TlsFileError::File {
        what,
        path: path.to_path_buf(),
        why: why.to_string(),
    }
}

fn settings_err(why: impl ToString) -> TlsFileError {
    TlsFileError::Settings(why.to_string())
}

fn certs(what: &'static str, path: &Path) -> Result<Vec<CertificateDer<'static>>, TlsFileError> {
    let v = CertificateDer::pem_file_iter(path)
        .map_err(|e| file_err(what, path, e))?
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| file_err(what, path, e))?;
    if v.is_empty() {
        return Err(file_err(what, path, "no PEM certificate in the file"));
    }
    Ok(v)
}

fn provider() -> Arc<rustls::crypto::CryptoProvider> {
    Arc::new(rustls::crypto::ring::default_provider())
}

impl Tls {
    /// The TLS of a node from its files: None when none is given (plain
    /// TCP). A node that accepts needs a certificate and key; one that
    /// only connects (a client) needs the authority alone.
    pub fn load(files: &TlsFiles, accepts: bool) -> Result<Option<Tls>, TlsFileError> {
        if !files.is_set() {
            return Ok(None);
        }
        let pair = match (&files.cert, &files.key) {
            (Some(c), Some(k)) => Some((certs("certificate", c)?, c, k)),
            (None, None) if !accepts => None,
            (c, _) => {
                let missing = if c.is_none() { "certificate" } else { "key" };
                let why = format!(
                    "a node that accepts connections needs both a certificate and its key \
                     (--tls-cert and --tls-key, or cert and key under [tls]); the {missing} is not given"
                );
                return Err(settings_err(why));
            }
        };
        let acceptor = match &pair {
            Some((chain, _, key_path)) => {
                let key = PrivateKeyDer::from_pem_file(key_path)
                    .map_err(|e| file_err("key", key_path, e))?;
                let cfg = rustls::ServerConfig::builder_with_provider(provider())
                    .with_safe_default_protocol_versions()
                    .map_err(settings_err)?
                    .with_no_client_auth()
                    .with_single_cert(chain.clone(), key)
                    .map_err(|e| file_err("key", key_path, e))?;
                Some(TlsAcceptor::from(Arc::new(cfg)))
            }
            None => None,
        };
        let (ca_path, anchors) = match (&files.ca, &pair) {
            (Some(p), _) => (p.clone(), certs("authority", p)?),
            (None, Some((chain, c, _))) => ((*c).clone(), chain.clone()),
            (None, None) => unreachable!("is_set with no cert, key or ca"),
        };
        let mut roots = rustls::RootCertStore::empty();
        for a in anchors {
            roots
                .add(a)
                .map_err(|e| file_err("authority", &ca_path, e))?;
        }
        let cfg = rustls::ClientConfig::builder_with_provider(provider())
            .with_safe_default_protocol_versions()
            .map_err(settings_err)?
            .with_root_certificates(roots)
            .with_no_client_auth();
        let name = files.server_name.as_deref().unwrap_or(SERVER_NAME);
        let name = ServerName::try_from(name.to_string())
            .map_err(|e| settings_err(format!("server name {name:?}: {e}")))?;
        Ok(Some(Tls {
            acceptor,
            connector: TlsConnector::from(Arc::new(cfg)),
            name,
        }))
    }

    /// The server side of TLS on an accepted connection.
    pub async fn accept(&self, tcp: TcpStream, peer: SocketAddr) -> Result<Stream, ProtocolError> {
        let Some(a) = &self.acceptor else {
            return Err(ProtocolError::Tls {
                peer,
                message: "this node has no certificate to accept with".into(),
                fatal: true,
            });
        };
        match a.accept(tcp).await {
            Ok(s) => Ok(Stream::Tls(Box::new(s.into()))),
            Err(e) => Err(failed(peer, &e, "is the peer set up for TLS?")),
        }
    }

    /// The client side of TLS on a connection made to `peer`.
    pub async fn connect(&self, tcp: TcpStream, peer: SocketAddr) -> Result<Stream, ProtocolError> {
        match self.connector.connect(self.name.clone(), tcp).await {
            Ok(s) => Ok(Stream::Tls(Box::new(s.into()))),
            Err(e) => Err(failed(
                peer,
                &e,
                "does the peer serve TLS, with a certificate of this farm's authority?",
            )),
        }
    }
}

/// A failed TLS handshake: fatal when TLS itself refused (a certificate
/// of another authority, no common protocol), which trying again cannot
/// mend; otherwise the link broke or the peer does not speak TLS, and the
/// hint says so.
fn failed(peer: SocketAddr, e: &std::io::Error, hint: &str) -> ProtocolError {
    match e.get_ref().and_then(|i| i.downcast_ref::<rustls::Error>()) {
        Some(r) => ProtocolError::Tls {
            peer,
            message: format!("TLS handshake failed: {r}"),
            fatal: true,
        },
        None => ProtocolError::Tls {
            peer,
            message: format!("TLS handshake failed: {e} ({hint})"),
            fatal: false,
        },
    }
}

/// A certificate for [`SERVER_NAME`], self-signed, and its key, both PEM:
/// what `locus tls-init` writes for a farm.
pub fn generate() -> Result<(String, String), String> {
    let ck = rcgen::generate_simple_self_signed(vec![SERVER_NAME.to_string()])
        .map_err(|e| e.to_string())?;
    Ok((ck.cert.pem(), ck.signing_key.serialize_pem()))
}
