//! TLS for gRPC and HTTP (rustls with ring): the server's certificate and key,
//! and, when `tls.client_ca_path` is set, client certificates signed by that CA
//! required on both (mutual TLS). Files are PEM; a problem with one is a start-up
//! error naming the file.

use std::sync::Arc;

use rustls_pki_types::pem::PemObject;
use rustls_pki_types::{CertificateDer, PrivateKeyDer};
use tokio_rustls::rustls;

use crate::config::TlsConfig;

/// The PEM files of `TlsConfig`, read once.
pub struct TlsFiles {
    pub cert: Vec<u8>,
    pub key: Vec<u8>,
    pub client_ca: Option<Vec<u8>>,
}

fn read(key: &str, path: &str) -> Result<Vec<u8>, String> {
    std::fs::read(path).map_err(|e| format!("{key} {path}: {e}"))
}

impl TlsFiles {
    /// `None` when TLS is off (no certificate configured).
    pub fn load(c: &TlsConfig) -> Result<Option<Self>, String> {
        if c.cert_path.is_empty() {
            return Ok(None);
        }
        let client_ca = match c.client_ca_path.as_str() {
            "" => None,
            path => Some(read("tls.client_ca_path", path)?),
        };
        Ok(Some(Self { cert: read("tls.cert_path", &c.cert_path)?, key: read("tls.key_path", &c.key_path)?, client_ca }))
    }

    /// The gRPC server's TLS settings.
    pub fn grpc(&self) -> tonic::transport::ServerTlsConfig {
        let mut tls = tonic::transport::ServerTlsConfig::new().identity(tonic::transport::Identity::from_pem(&self.cert, &self.key));
        if let Some(ca) = &self.client_ca {
            tls = tls.client_ca_root(tonic::transport::Certificate::from_pem(ca));
        }
        tls
    }

    /// The HTTP server's acceptor (HTTP/2 and HTTP/1.1 by ALPN).
    pub fn http(&self) -> Result<tokio_rustls::TlsAcceptor, String> {
        let certs = CertificateDer::pem_slice_iter(&self.cert).collect::<Result<Vec<_>, _>>().map_err(|e| format!("tls.cert_path: {e}"))?;
        if certs.is_empty() {
            return Err("tls.cert_path holds no certificate".into());
        }
        let key = PrivateKeyDer::from_pem_slice(&self.key).map_err(|e| format!("tls.key_path: {e}"))?;
        let provider = Arc::new(rustls::crypto::ring::default_provider());
        let builder = rustls::ServerConfig::builder_with_provider(provider.clone())
            .with_safe_default_protocol_versions()
            .map_err(|e| e.to_string())?;
        let builder = match &self.client_ca {
            None => builder.with_no_client_auth(),
            Some(ca) => {
                let mut roots = rustls::RootCertStore::empty();
                for cert in CertificateDer::pem_slice_iter(ca) {
                    roots.add(cert.map_err(|e| format!("tls.client_ca_path: {e}"))?).map_err(|e| format!("tls.client_ca_path: {e}"))?;
                }
                let verifier = rustls::server::WebPkiClientVerifier::builder_with_provider(Arc::new(roots), provider)
                    .build()
                    .map_err(|e| format!("tls.client_ca_path: {e}"))?;
                builder.with_client_cert_verifier(verifier)
            }
        };
        let mut config = builder.with_single_cert(certs, key).map_err(|e| format!("tls.cert_path / tls.key_path: {e}"))?;
        config.alpn_protocols = vec![b"h2".to_vec(), b"http/1.1".to_vec()];
        Ok(tokio_rustls::TlsAcceptor::from(Arc::new(config)))
    }
}
