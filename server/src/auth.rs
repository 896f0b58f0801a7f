//! Robot authentication: the bearer token of a hello (`Hello.auth_token`) checked
//! against `auth.tokens`. Both ingest shells (gRPC, Zenoh) ask [`Tokens::check`]
//! before a session is opened or resumed; a refusal is `UNAUTHENTICATED`.
//! Whole-map import and export over HTTP ask [`Admin::check`] (`auth.admin_tokens`).

use stillmap_proto::pb;
use tonic::Status;

/// The tokens a hello may carry; none configured: every hello is accepted.
#[derive(Debug, Default)]
pub struct Tokens(Vec<Vec<u8>>);

impl Tokens {
    pub fn new(tokens: &[String]) -> Self {
        Self(tokens.iter().map(|t| t.as_bytes().to_vec()).collect())
    }

    /// Whether tokens are required at all.
    pub fn required(&self) -> bool {
        !self.0.is_empty()
    }

    /// `Ok` when no token is configured or the hello carries one of them.
    pub fn check(&self, hello: &pb::Hello) -> Result<(), Status> {
        if !self.required() {
            return Ok(());
        }
        if hello.auth_token.is_empty() {
            return Err(Status::unauthenticated("this server requires an auth token in the hello (stillmap-client --token)"));
        }
        if self.matches(hello.auth_token.as_bytes()) { Ok(()) } else { Err(Status::unauthenticated("unknown auth token")) }
    }

    /// Whether `given` is one of the tokens. Every configured token is compared in
    /// full, whatever matches, so the time taken does not tell how much of a guess
    /// was right.
    fn matches(&self, given: &[u8]) -> bool {
        self.0.iter().fold(false, |found, token| found | constant_time_eq(token, given))
    }
}

/// Who may move whole maps in and out (`POST /api/v1/maps/import`,
/// `GET /api/v1/maps/{id}/export`): an `Authorization: Bearer` header with one of
/// `auth.admin_tokens`, whenever any token is configured.
#[derive(Debug, Default)]
pub struct Admin {
    admins: Tokens,
    robots: Tokens,
}

/// Why an admin request was refused (HTTP 401 / 403).
#[derive(Debug, PartialEq, Eq, thiserror::Error)]
pub enum AdminRefusal {
    #[error("this needs an admin token: Authorization: Bearer <token> (auth.admin_tokens)")]
    Missing,
    #[error("unknown token")]
    Unknown,
    #[error("a robot token cannot import or export maps (auth.admin_tokens)")]
    RobotToken,
}

impl Admin {
    pub fn new(admin_tokens: &[String], robot_tokens: &[String]) -> Self {
        Self { admins: Tokens::new(admin_tokens), robots: Tokens::new(robot_tokens) }
    }

    /// `Ok` when no token is configured at all, or `authorization` (the header's
    /// value) carries an admin token.
    pub fn check(&self, authorization: Option<&[u8]>) -> Result<(), AdminRefusal> {
        if !self.admins.required() && !self.robots.required() {
            return Ok(());
        }
        let token = authorization.and_then(|v| v.strip_prefix(b"Bearer ")).ok_or(AdminRefusal::Missing)?;
        if self.admins.matches(token) {
            Ok(())
        } else if self.robots.matches(token) {
            Err(AdminRefusal::RobotToken)
        } else {
            Err(AdminRefusal::Unknown)
        }
    }
}

/// A new session's resume secret: 128 random bits, hex.
pub fn new_secret() -> Result<String, getrandom::Error> {
    let mut bytes = [0u8; 16];
    getrandom::fill(&mut bytes)?;
    Ok(bytes.iter().map(|b| format!("{b:02x}")).collect())
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

    fn hello(token: &str) -> pb::Hello {
        pb::Hello { robot_id: "r".into(), auth_token: token.into(), ..Default::default() }
    }

    #[test]
    fn no_tokens_accept_everyone_and_tokens_admit_only_their_holders() {
        assert!(Tokens::default().check(&hello("")).is_ok());
        assert!(Tokens::default().check(&hello("anything")).is_ok());
        let tokens = Tokens::new(&["alpha-1".into(), "beta-22".into()]);
        assert!(tokens.check(&hello("alpha-1")).is_ok());
        assert!(tokens.check(&hello("beta-22")).is_ok());
        let missing = tokens.check(&hello("")).unwrap_err();
        assert_eq!(missing.code(), tonic::Code::Unauthenticated);
        assert_eq!(missing.message(), "this server requires an auth token in the hello (stillmap-client --token)");
        for wrong in ["alpha-2", "alpha-1 ", "alpha", "beta-22x"] {
            let e = tokens.check(&hello(wrong)).unwrap_err();
            assert_eq!((e.code(), e.message()), (tonic::Code::Unauthenticated, "unknown auth token"), "{wrong:?}");
        }
    }

    #[test]
    fn import_and_export_need_an_admin_token_once_any_token_is_configured() {
        let open = Admin::new(&[], &[]);
        assert_eq!(open.check(None), Ok(()));
        let robots_only = Admin::new(&[], &["robot-1".into()]);
        assert_eq!(robots_only.check(None), Err(AdminRefusal::Missing));
        assert_eq!(robots_only.check(Some(b"Bearer robot-1")), Err(AdminRefusal::RobotToken));
        let admin = Admin::new(&["root-9".into()], &["robot-1".into()]);
        assert_eq!(admin.check(Some(b"Bearer root-9")), Ok(()));
        assert_eq!(admin.check(Some(b"root-9")), Err(AdminRefusal::Missing));
        assert_eq!(admin.check(Some(b"Bearer root-")), Err(AdminRefusal::Unknown));
        assert_eq!(admin.check(Some(b"Bearer robot-1")), Err(AdminRefusal::RobotToken));
        assert_eq!(Admin::new(&["root-9".into()], &[]).check(None), Err(AdminRefusal::Missing));
    }
}
