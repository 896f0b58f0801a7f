//! Rate limits per client (issue 21): hellos per peer address (gRPC) or robot id
//! (Zenoh, which carries no peer address), and HTTP requests per bearer token or
//! peer address. Token buckets (`governor`'s GCRA): a client may send a burst,
//! then at the configured rate. Clients quiet long enough to have a full bucket
//! again are forgotten ([`RateLimits::forget_idle`]), so the state is bounded by
//! the clients active recently.

use std::num::NonZeroU32;

use governor::{DefaultKeyedRateLimiter, Quota, RateLimiter};

use crate::config::LimitsConfig;

pub struct RateLimits {
    hellos: Option<(DefaultKeyedRateLimiter<String>, String)>,
    http: Option<(DefaultKeyedRateLimiter<String>, String)>,
}

/// A keyed limiter of `per_minute` with `burst` (none when the rate is 0).
fn limiter(per_minute: u32, burst: u32, what: String) -> Option<(DefaultKeyedRateLimiter<String>, String)> {
    let rate = NonZeroU32::new(per_minute)?;
    let burst = NonZeroU32::new(burst).unwrap_or(NonZeroU32::MIN);
    Some((RateLimiter::keyed(Quota::per_minute(rate).allow_burst(burst)), what))
}

impl RateLimits {
    pub fn new(l: &LimitsConfig) -> Self {
        Self {
            hellos: limiter(
                l.hellos_per_minute,
                l.hello_burst,
                format!("limits.hellos_per_minute = {}, limits.hello_burst = {}", l.hellos_per_minute, l.hello_burst),
            ),
            http: limiter(
                l.http_requests_per_minute,
                l.http_burst,
                format!("limits.http_requests_per_minute = {}, limits.http_burst = {}", l.http_requests_per_minute, l.http_burst),
            ),
        }
    }

    /// Counts a hello from `client`; `Err` names the limit when it is over.
    pub fn hello(&self, client: &str) -> Result<(), String> {
        check(&self.hellos, client, &format!("hellos from {client}"))
    }

    /// Counts an HTTP request from `client` (a bearer token: `shown` says who it is
    /// in the answer without echoing it); `Err` names the limit when it is over.
    pub fn http(&self, client: &str, shown: &str) -> Result<(), String> {
        check(&self.http, client, &format!("requests from {shown}"))
    }

    /// Forgets the clients whose bucket is full again (quiet long enough).
    pub fn forget_idle(&self) {
        for (limiter, _) in [&self.hellos, &self.http].into_iter().flatten() {
            limiter.retain_recent();
            limiter.shrink_to_fit();
        }
    }
}

fn check(limiter: &Option<(DefaultKeyedRateLimiter<String>, String)>, client: &str, what: &str) -> Result<(), String> {
    match limiter {
        Some((l, limit)) if l.check_key(&client.to_string()).is_err() => Err(format!("too many {what}: {limit}")),
        _ => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_burst_passes_then_the_limit_names_itself_per_client() {
        let limits =
            RateLimits::new(&LimitsConfig { hellos_per_minute: 1, hello_burst: 3, http_requests_per_minute: 0, ..LimitsConfig::default() });
        for _ in 0..3 {
            assert_eq!(limits.hello("ip 10.0.0.1"), Ok(()));
        }
        assert_eq!(
            limits.hello("ip 10.0.0.1"),
            Err("too many hellos from ip 10.0.0.1: limits.hellos_per_minute = 1, limits.hello_burst = 3".into())
        );
        assert_eq!(limits.hello("ip 10.0.0.2"), Ok(()), "another client has its own bucket");
        for _ in 0..10_000 {
            assert_eq!(limits.http("ip 10.0.0.1", "10.0.0.1"), Ok(()), "0: no limit");
        }
        limits.forget_idle();
        assert!(limits.hello("ip 10.0.0.1").is_err(), "not quiet long enough to be forgotten");
    }
}
