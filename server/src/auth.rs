//! Who may do what. A token carries scopes:
//!
//! - `robot:<glob>`: open and resume sessions as a robot whose id matches the glob
//!   (`*` any run of characters, `?` one, `[...]` a class);
//! - `read`: the query APIs (HTTP `/api/v1/...`, `/metrics`, the dashboard's event
//!   stream, gRPC `Query`);
//! - `admin`: whole maps in and out (import, export); it implies `read`.
//!
//! Tokens come from the config (`auth.tokens`: `robot:*`; `auth.read_tokens`:
//! `read`; `auth.admin_tokens`: `admin`) and from `auth.token_file` (one token and
//! its scopes per line), which SIGHUP reloads without a restart. No token anywhere:
//! everything is open (a trusted network). Tokens are compared in constant time
//! and never logged.

use std::sync::{Arc, RwLock};

use stillmap_proto::pb;
use tonic::Status;

use crate::config::AuthConfig;

/// What one token may do.
#[derive(Debug)]
struct Grant {
    secret: Vec<u8>,
    robots: Vec<glob::Pattern>,
    read: bool,
    admin: bool,
}

impl Grant {
    fn may_stream(&self, robot_id: &str) -> bool {
        self.robots.iter().any(|p| p.matches(robot_id))
    }
}

/// What a request needs beyond a known token.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Need {
    Read,
    Admin,
}

impl Need {
    fn scope(self) -> &'static str {
        match self {
            Self::Read => "read",
            Self::Admin => "admin",
        }
    }
}

/// Why a query or an admin request was refused.
#[derive(Debug, PartialEq, Eq, thiserror::Error)]
pub enum Refusal {
    #[error("this needs a token with the {0} scope: Authorization: Bearer <token>")]
    Missing(&'static str),
    #[error("unknown token")]
    Unknown,
    #[error("this token lacks the {0} scope")]
    Scope(&'static str),
}

impl Refusal {
    /// 401 for no or an unknown token, 403 for a token without the scope.
    pub fn http_status(&self) -> u16 {
        match self {
            Self::Missing(_) | Self::Unknown => 401,
            Self::Scope(_) => 403,
        }
    }

    pub fn grpc_status(&self) -> Status {
        match self {
            Self::Missing(_) | Self::Unknown => Status::unauthenticated(self.to_string()),
            Self::Scope(_) => Status::permission_denied(self.to_string()),
        }
    }
}

/// The tokens in force.
#[derive(Debug, Default)]
pub struct Auth {
    grants: Vec<Grant>,
}

impl Auth {
    /// The config's tokens, and those of `token_file` (its text) when given.
    pub fn new(config: &AuthConfig, token_file: Option<&str>) -> Result<Self, String> {
        let plain = |tokens: &[String], robots: &[&str], read: bool, admin: bool| -> Result<Vec<Grant>, String> {
            tokens
                .iter()
                .map(|t| {
                    let robots = robots.iter().map(|g| glob::Pattern::new(g).map_err(|e| e.to_string())).collect::<Result<_, _>>()?;
                    Ok(Grant { secret: t.as_bytes().to_vec(), robots, read, admin })
                })
                .collect()
        };
        let mut grants = plain(&config.tokens, &["*"], false, false)?;
        grants.extend(plain(&config.read_tokens, &[], true, false)?);
        grants.extend(plain(&config.admin_tokens, &[], true, true)?);
        if let Some(text) = token_file {
            grants.extend(parse_token_file(text)?);
        }
        Ok(Self { grants })
    }

    /// Whether tokens are required at all.
    pub fn required(&self) -> bool {
        !self.grants.is_empty()
    }

    /// The grant of `token`. Every grant is compared in full, whatever matches, so
    /// the time taken does not tell how much of a guess was right.
    fn find(&self, token: &[u8]) -> Option<&Grant> {
        self.grants.iter().fold(None, |found, g| if constant_time_eq(&g.secret, token) { Some(g) } else { found })
    }

    /// Whether `authorization` (`Bearer <token>`) carries a configured token.
    pub fn known(&self, authorization: Option<&[u8]>) -> bool {
        authorization.and_then(|v| v.strip_prefix(b"Bearer ")).is_some_and(|t| self.find(t).is_some())
    }

    /// `Ok` when no token is configured, or the hello carries a token that may
    /// stream as its robot (UNAUTHENTICATED without a known token, PERMISSION_DENIED
    /// for another robot's token).
    pub fn check_hello(&self, hello: &pb::Hello) -> Result<(), Status> {
        if !self.required() {
            return Ok(());
        }
        if hello.auth_token.is_empty() {
            return Err(Status::unauthenticated("this server requires an auth token in the hello (stillmap-client --token)"));
        }
        match self.find(hello.auth_token.as_bytes()) {
            None => Err(Status::unauthenticated("unknown auth token")),
            Some(g) if g.may_stream(&hello.robot_id) => Ok(()),
            Some(_) => Err(Status::permission_denied(format!(
                "this token may not stream as robot {:?} (its robot:<glob> scopes do not match)",
                hello.robot_id
            ))),
        }
    }

    /// `Ok` when no token is configured, or `authorization` (an `Authorization`
    /// header's or gRPC metadata's value, `Bearer <token>`) carries a token with `need`.
    pub fn check(&self, authorization: Option<&[u8]>, need: Need) -> Result<(), Refusal> {
        if !self.required() {
            return Ok(());
        }
        let token = authorization.and_then(|v| v.strip_prefix(b"Bearer ")).ok_or(Refusal::Missing(need.scope()))?;
        let grant = self.find(token).ok_or(Refusal::Unknown)?;
        let allowed = match need {
            Need::Read => grant.read,
            Need::Admin => grant.admin,
        };
        if allowed { Ok(()) } else { Err(Refusal::Scope(need.scope())) }
    }
}

/// A token file: one token per line followed by its scopes (`robot:<glob>`, `read`,
/// `admin`), separated by spaces; `#` starts a comment. A mistake names its line
/// (never the token).
fn parse_token_file(text: &str) -> Result<Vec<Grant>, String> {
    let mut grants = Vec::new();
    for (n, line) in text.lines().enumerate() {
        let line = line.split('#').next().unwrap_or("").trim();
        if line.is_empty() {
            continue;
        }
        let mut words = line.split_whitespace();
        let secret = words.next().unwrap_or_default().as_bytes().to_vec();
        let mut grant = Grant { secret, robots: Vec::new(), read: false, admin: false };
        for scope in words {
            match scope {
                "read" => grant.read = true,
                "admin" => (grant.read, grant.admin) = (true, true),
                _ => match scope.strip_prefix("robot:") {
                    Some(g) if !g.is_empty() => {
                        grant.robots.push(glob::Pattern::new(g).map_err(|e| format!("line {}: bad robot glob {g:?}: {e}", n + 1))?)
                    }
                    _ => return Err(format!("line {}: unknown scope {scope:?} (robot:<glob>, read or admin)", n + 1)),
                },
            }
        }
        if grant.robots.is_empty() && !grant.read {
            return Err(format!("line {}: a token needs at least one scope (robot:<glob>, read or admin)", n + 1));
        }
        grants.push(grant);
    }
    Ok(grants)
}

/// The tokens in force, replaced whole by [`reload`](Self::reload) (SIGHUP).
pub struct AuthHandle {
    config: AuthConfig,
    current: RwLock<Arc<Auth>>,
}

impl AuthHandle {
    /// Reads `auth.token_file` when set; any mistake is an error.
    pub fn new(config: &AuthConfig) -> Result<Self, String> {
        let auth = Self::load(config)?;
        Ok(Self { config: config.clone(), current: RwLock::new(Arc::new(auth)) })
    }

    fn load(config: &AuthConfig) -> Result<Auth, String> {
        let file = match config.token_file.as_str() {
            "" => None,
            path => Some(std::fs::read_to_string(path).map_err(|e| format!("auth.token_file {path}: {e}"))?),
        };
        Auth::new(config, file.as_deref()).map_err(|e| match config.token_file.as_str() {
            "" => e,
            path => format!("auth.token_file {path}: {e}"),
        })
    }

    pub fn get(&self) -> Arc<Auth> {
        crate::read(&self.current).clone()
    }

    /// Reads the token file again; on a mistake the tokens in force stay. Returns
    /// how many tokens are in force.
    pub fn reload(&self) -> Result<usize, String> {
        let auth = Self::load(&self.config)?;
        let n = auth.grants.len();
        *crate::write(&self.current) = Arc::new(auth);
        Ok(n)
    }
}

/// A new session's resume secret: 128 random bits, hex.
pub fn new_secret() -> Result<String, getrandom::Error> {
    let mut bytes = [0u8; 16];
    getrandom::fill(&mut bytes)?;
    Ok(bytes.iter().map(|b| format!("{b:02x}")).collect())
}

/// Whether two secrets' bytes (hashes) are the same (never for empty ones), in constant time.
pub fn same_secret_bytes(secret: &[u8], given: &[u8]) -> bool {
    !secret.is_empty() && constant_time_eq(secret, given)
}

/// Whether `given` is `secret` (never for an empty secret), in constant time.
pub fn same_secret(secret: &str, given: &str) -> bool {
    !secret.is_empty() && constant_time_eq(secret.as_bytes(), given.as_bytes())
}

/// Byte equality whose time depends on the lengths only.
fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
    if a.len() != b.len() {
        return false;
    }
    a.iter().zip(b).fold(0u8, |diff, (x, y)| diff | (x ^ y)) == 0
}

#[cfg(test)]
mod tests {
    use super::*;

    fn hello(robot: &str, token: &str) -> pb::Hello {
        pb::Hello { robot_id: robot.into(), auth_token: token.into(), ..Default::default() }
    }

    fn config(tokens: &[&str], read: &[&str], admin: &[&str]) -> AuthConfig {
        let owned = |t: &[&str]| t.iter().map(|s| s.to_string()).collect();
        AuthConfig { tokens: owned(tokens), read_tokens: owned(read), admin_tokens: owned(admin), token_file: String::new() }
    }

    #[test]
    fn no_tokens_accept_everyone_and_tokens_admit_only_their_holders() {
        let open = Auth::default();
        assert!(open.check_hello(&hello("r", "")).is_ok());
        assert_eq!(open.check(None, Need::Admin), Ok(()));
        let auth = Auth::new(&config(&["alpha-1", "beta-22"], &[], &[]), None).unwrap();
        assert!(auth.check_hello(&hello("r", "alpha-1")).is_ok());
        assert!(auth.check_hello(&hello("r", "beta-22")).is_ok());
        let missing = auth.check_hello(&hello("r", "")).unwrap_err();
        assert_eq!(
            (missing.code(), missing.message()),
            (tonic::Code::Unauthenticated, "this server requires an auth token in the hello (stillmap-client --token)")
        );
        for wrong in ["alpha-2", "alpha-1 ", "alpha", "beta-22x"] {
            let e = auth.check_hello(&hello("r", wrong)).unwrap_err();
            assert_eq!((e.code(), e.message()), (tonic::Code::Unauthenticated, "unknown auth token"), "{wrong:?}");
        }
    }

    /// The scope matrix: a robot token for another robot, a read token on ingest, a
    /// robot token on queries, no token on import.
    #[test]
    fn scopes_decide_what_a_token_may_do() {
        let file = "# fleet tokens\nwh-token robot:warehouse-* \nviewer-token read\nops-token admin # the operators\nboth-token robot:lab-? read\n";
        let auth = Auth::new(&config(&["any-robot"], &["reader"], &["root"]), Some(file)).unwrap();
        assert!(auth.check_hello(&hello("warehouse-7", "wh-token")).is_ok());
        let other = auth.check_hello(&hello("lab-1", "wh-token")).unwrap_err();
        assert_eq!(other.code(), tonic::Code::PermissionDenied);
        assert_eq!(other.message(), "this token may not stream as robot \"lab-1\" (its robot:<glob> scopes do not match)");
        assert_eq!(
            auth.check_hello(&hello("lab-1", "viewer-token")).unwrap_err().code(),
            tonic::Code::PermissionDenied,
            "a read token on ingest"
        );
        assert!(auth.check_hello(&hello("lab-1", "both-token")).is_ok());
        assert!(auth.check_hello(&hello("lab-12", "both-token")).is_err());
        assert!(auth.check_hello(&hello("anything", "any-robot")).is_ok());
        let bearer = |t: &str| format!("Bearer {t}").into_bytes();
        assert_eq!(auth.check(Some(&bearer("viewer-token")), Need::Read), Ok(()));
        assert_eq!(auth.check(Some(&bearer("reader")), Need::Read), Ok(()));
        assert_eq!(auth.check(Some(&bearer("both-token")), Need::Read), Ok(()));
        assert_eq!(auth.check(Some(&bearer("any-robot")), Need::Read), Err(Refusal::Scope("read")), "a robot token on queries");
        assert_eq!(auth.check(Some(&bearer("viewer-token")), Need::Admin), Err(Refusal::Scope("admin")));
        assert_eq!(auth.check(Some(&bearer("ops-token")), Need::Admin), Ok(()));
        assert_eq!(auth.check(Some(&bearer("root")), Need::Read), Ok(()), "admin implies read");
        assert_eq!(auth.check(None, Need::Admin), Err(Refusal::Missing("admin")), "no token on import");
        assert_eq!(auth.check(Some(b"root"), Need::Admin), Err(Refusal::Missing("admin")), "not a bearer header");
        assert_eq!(auth.check(Some(&bearer("roo")), Need::Read), Err(Refusal::Unknown));
        assert_eq!((Refusal::Unknown.http_status(), Refusal::Scope("read").http_status()), (401, 403));
        assert!(
            auth.known(Some(&bearer("wh-token")))
                && !auth.known(Some(&bearer("guess")))
                && !auth.known(Some(b"wh-token"))
                && !auth.known(None)
        );
    }

    #[test]
    fn token_file_mistakes_name_their_line_never_the_token() {
        for (text, error) in [
            ("t1 read\nsecret-2 writer\n", "line 2: unknown scope \"writer\" (robot:<glob>, read or admin)"),
            ("secret-1\n", "line 1: a token needs at least one scope (robot:<glob>, read or admin)"),
            ("\n\nsecret-3 robot:\n", "line 3: unknown scope \"robot:\" (robot:<glob>, read or admin)"),
        ] {
            let e = Auth::new(&AuthConfig::default(), Some(text)).unwrap_err();
            assert_eq!(e, error);
            assert!(!e.contains("secret"), "{e}");
        }
        assert!(Auth::new(&AuthConfig::default(), Some("secret-4 robot:[a-\n")).unwrap_err().starts_with("line 1: bad robot glob"));
    }

    /// SIGHUP reloads the token file; a broken file keeps the tokens in force.
    #[test]
    fn reload_replaces_the_tokens_and_keeps_them_on_a_mistake() {
        let path = std::env::temp_dir().join(format!("stillmap-tokens-{}.txt", std::process::id()));
        std::fs::write(&path, "old-token read\n").unwrap();
        let handle = AuthHandle::new(&AuthConfig { token_file: path.display().to_string(), ..AuthConfig::default() }).unwrap();
        assert_eq!(handle.get().check(Some(b"Bearer old-token"), Need::Read), Ok(()));
        std::fs::write(&path, "new-token read\nrobot-token robot:r-*\n").unwrap();
        assert_eq!(handle.reload(), Ok(2));
        assert_eq!(handle.get().check(Some(b"Bearer old-token"), Need::Read), Err(Refusal::Unknown));
        assert_eq!(handle.get().check(Some(b"Bearer new-token"), Need::Read), Ok(()));
        std::fs::write(&path, "new-token reed\n").unwrap();
        assert!(handle.reload().unwrap_err().ends_with("line 1: unknown scope \"reed\" (robot:<glob>, read or admin)"));
        assert_eq!(handle.get().check(Some(b"Bearer new-token"), Need::Read), Ok(()), "kept");
        let _ = std::fs::remove_file(&path);
    }
}
