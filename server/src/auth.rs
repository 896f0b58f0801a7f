//! Robot authentication: the bearer token of a hello (`Hello.auth_token`) checked
//! against `auth.tokens`. Both ingest shells (gRPC, Zenoh) ask [`Tokens::check`]
//! before a session is opened or resumed; a refusal is `UNAUTHENTICATED`.

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
        let given = hello.auth_token.as_bytes();
        // Every configured token is compared in full, whatever matches, so the time
        // taken does not tell how much of a guess was right.
        let matched = self.0.iter().fold(false, |found, token| found | constant_time_eq(token, given));
        if matched { Ok(()) } else { Err(Status::unauthenticated("unknown auth token")) }
    }
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
}
