//! What the [`FaultProxy`](super::FaultProxy) does to each request: the plan (latency,
//! bandwidth, fault probabilities and where they apply), the counters it keeps, and the
//! deterministic choice of a request's fault. The choice hashes the seed with the
//! request's key and how often that key was seen, so a plan injects the same faults on
//! every run whatever order concurrent requests arrive in.

use std::collections::{HashMap, HashSet};
use std::ops::Range;
use std::time::Duration;

/// Which requests a plan's faults may hit (latency and bandwidth apply to all).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum FaultScope {
    /// Every request.
    #[default]
    All,
    /// Object GETs, ranged or not.
    ObjectGets,
    /// Object GETs with a `Range` header only.
    RangedGets,
    /// LIST requests (`GET` with `list-type=2`) only.
    Lists,
    /// Only the Nth request the proxy receives after the plan was set (1 = the first).
    NthRequest(u64),
}

/// The faults and slowness the proxy applies, per request.
///
/// Fault probabilities are tried in the order of the fields (one uniform draw per
/// request); their sum must not exceed 1.
#[derive(Debug, Clone, PartialEq)]
pub struct FaultPlan {
    /// Added before the first byte of each response (injected errors included).
    pub latency: Duration,
    /// Cap on the response bodies forwarded, one budget shared by all connections (as one
    /// link would be); `None`: no cap.
    pub bandwidth_bytes_per_sec: Option<u64>,
    /// Answer `503 Service Unavailable` with S3's `SlowDown` error, without asking upstream.
    pub p_503: f64,
    /// Answer `500 Internal Server Error` with S3's `InternalError`, without asking upstream.
    pub p_500: f64,
    /// Close the connection without any response (the request is not forwarded).
    pub p_reset: f64,
    /// Forward the status, the headers and half of the body, then close.
    pub p_cut: f64,
    /// Wait [`slow_first_byte`](Self::slow_first_byte) more before the first byte.
    pub p_slow_first_byte: f64,
    /// The extra wait of a slow first byte.
    pub slow_first_byte: Duration,
    /// Which requests faults may hit.
    pub scope: FaultScope,
    /// Fault each distinct request (method, target with its query, `Range` header) at
    /// most once: its retry goes through. "10 % of GETs fail once" is `p_503: 0.1` with this.
    pub fail_once: bool,
    /// Seed of the fault choice.
    pub seed: u64,
}

impl Default for FaultPlan {
    /// No latency, no cap, no faults.
    fn default() -> Self {
        Self {
            latency: Duration::ZERO,
            bandwidth_bytes_per_sec: None,
            p_503: 0.0,
            p_500: 0.0,
            p_reset: 0.0,
            p_cut: 0.0,
            p_slow_first_byte: 0.0,
            slow_first_byte: Duration::from_secs(2),
            scope: FaultScope::All,
            fail_once: false,
            seed: 0x5eed_5eed,
        }
    }
}

/// A plan the proxy cannot apply.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PlanError {
    /// A probability outside [0, 1].
    #[error("fault probability {name} = {value} is not in [0, 1]")]
    Probability {
        /// The field.
        name: &'static str,
        /// Its value.
        value: f64,
    },
    /// Probabilities adding up to more than 1.
    #[error("fault probabilities add up to {0} > 1")]
    Sum(f64),
    /// A bandwidth of zero bytes per second.
    #[error("bandwidth_bytes_per_sec must be > 0")]
    ZeroBandwidth,
}

impl FaultPlan {
    /// Only a latency per request.
    pub fn latency(latency: Duration) -> Self {
        Self {
            latency,
            ..Self::default()
        }
    }

    /// Checks the probabilities and the bandwidth.
    pub fn validate(&self) -> Result<(), PlanError> {
        let probabilities = [
            ("p_503", self.p_503),
            ("p_500", self.p_500),
            ("p_reset", self.p_reset),
            ("p_cut", self.p_cut),
            ("p_slow_first_byte", self.p_slow_first_byte),
        ];
        for (name, value) in probabilities {
            if !(0.0..=1.0).contains(&value) {
                return Err(PlanError::Probability { name, value });
            }
        }
        let sum: f64 = probabilities.iter().map(|(_, p)| p).sum();
        if sum > 1.0 + 1e-9 {
            return Err(PlanError::Sum(sum));
        }
        if self.bandwidth_bytes_per_sec == Some(0) {
            return Err(PlanError::ZeroBandwidth);
        }
        Ok(())
    }
}

/// What a request is, as the counters tell them apart.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RequestKind {
    /// `GET` of an object without `Range`.
    GetObject,
    /// `GET` of an object with `Range`.
    RangedGet,
    /// `HEAD`.
    Head,
    /// `GET` with `list-type=2` in the query (ListObjectsV2).
    List,
    /// `PUT` (objects, parts, buckets).
    Put,
    /// Anything else (`DELETE`, `POST`, other `GET`s).
    Other,
}

impl RequestKind {
    /// The kind of a request from its method, target (path and query) and whether it
    /// carries a `Range` header. Path-style addressing: `/bucket/key` is an object.
    pub fn classify(method: &str, target: &str, ranged: bool) -> Self {
        let (path, query) = target.split_once('?').unwrap_or((target, ""));
        match method {
            "HEAD" => Self::Head,
            "PUT" => Self::Put,
            "GET" if query.split('&').any(|p| p == "list-type=2") => Self::List,
            "GET" if query.is_empty() && is_object_path(path) => {
                if ranged {
                    Self::RangedGet
                } else {
                    Self::GetObject
                }
            }
            _ => Self::Other,
        }
    }
}

/// `/bucket/key…` with a non-empty key.
fn is_object_path(path: &str) -> bool {
    path.trim_start_matches('/')
        .split_once('/')
        .is_some_and(|(bucket, key)| !bucket.is_empty() && !key.is_empty())
}

/// Faults injected, by kind.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct FaultCounts {
    /// `503 SlowDown` answers.
    pub status_503: u64,
    /// `500 InternalError` answers.
    pub status_500: u64,
    /// Connections closed without a response.
    pub reset: u64,
    /// Responses cut after half of the body.
    pub cut: u64,
    /// Responses whose first byte was delayed.
    pub slow_first_byte: u64,
}

impl FaultCounts {
    /// All faults.
    pub fn total(&self) -> u64 {
        self.status_503 + self.status_500 + self.reset + self.cut + self.slow_first_byte
    }
}

/// What the proxy saw since it started or since the last
/// [`reset_counters`](super::FaultProxy::reset_counters).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Counters {
    /// Object GETs without `Range`.
    pub get_object: u64,
    /// Object GETs with `Range`.
    pub ranged_get: u64,
    /// HEADs.
    pub head: u64,
    /// LISTs (ListObjectsV2 pages).
    pub list: u64,
    /// PUTs.
    pub put: u64,
    /// Other requests.
    pub other: u64,
    /// Response body bytes forwarded from upstream to clients (injected error bodies not
    /// included).
    pub body_bytes: u64,
    /// Object bytes that GETs asked for, each byte of an object counted once however
    /// many GETs covered it (the union of their ranges, from each response's
    /// `Content-Range`): `body_bytes` less what was read again.
    pub distinct_get_bytes: u64,
    /// Faults injected.
    pub faults: FaultCounts,
}

impl Counters {
    /// All requests received.
    pub fn requests(&self) -> u64 {
        self.get_object + self.ranged_get + self.head + self.list + self.put + self.other
    }

    /// Object GETs, ranged or not.
    pub fn gets(&self) -> u64 {
        self.get_object + self.ranged_get
    }

    fn count(&mut self, kind: RequestKind) {
        let slot = match kind {
            RequestKind::GetObject => &mut self.get_object,
            RequestKind::RangedGet => &mut self.ranged_get,
            RequestKind::Head => &mut self.head,
            RequestKind::List => &mut self.list,
            RequestKind::Put => &mut self.put,
            RequestKind::Other => &mut self.other,
        };
        *slot += 1;
    }
}

/// The fault chosen for one request.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Fault {
    Status503,
    Status500,
    Reset,
    Cut,
    SlowFirstByte,
}

/// The proxy's mutable state, behind one lock.
#[derive(Debug, Default)]
pub(crate) struct State {
    pub(crate) plan: FaultPlan,
    pub(crate) counters: Counters,
    /// Times each request key was seen since the plan was set.
    seen: HashMap<String, u64>,
    /// Keys already faulted since the plan was set.
    faulted: HashSet<String>,
    /// Requests since the plan was set.
    requests: u64,
    /// The byte ranges of each object (by path) that GETs were answered with since the
    /// counters were reset: sorted, disjoint, not touching.
    covered: HashMap<String, Vec<Range<u64>>>,
}

impl State {
    pub(crate) fn new(plan: FaultPlan) -> Self {
        Self {
            plan,
            ..Self::default()
        }
    }

    pub(crate) fn set_plan(&mut self, plan: FaultPlan) {
        self.plan = plan;
        self.seen.clear();
        self.faulted.clear();
        self.requests = 0;
    }

    /// Zeroes the counters (and forgets the ranges served).
    pub(crate) fn reset_counters(&mut self) {
        self.counters = Counters::default();
        self.covered.clear();
    }

    /// Adds `range` of `object` to the ranges served, counting its bytes not served
    /// before in [`Counters::distinct_get_bytes`].
    pub(crate) fn cover(&mut self, object: &str, range: Range<u64>) {
        let spans = self.covered.entry(object.to_owned()).or_default();
        let (mut start, mut end) = (range.start, range.end);
        let mut new = end.saturating_sub(start);
        // Merge every span that overlaps or touches `range`.
        let first = spans.partition_point(|s| s.end < start);
        let mut last = first;
        while last < spans.len() && spans[last].start <= end {
            let s = &spans[last];
            let overlap = s
                .end
                .min(range.end)
                .saturating_sub(s.start.max(range.start));
            new -= overlap;
            start = start.min(s.start);
            end = end.max(s.end);
            last += 1;
        }
        spans.splice(first..last, std::iter::once(start..end));
        self.counters.distinct_get_bytes += new;
    }

    /// Counts the request and chooses its fault.
    pub(crate) fn decide(&mut self, kind: RequestKind, key: &str) -> Option<Fault> {
        self.counters.count(kind);
        self.requests += 1;
        let seen = self.seen.entry(key.to_owned()).or_insert(0);
        let occurrence = *seen;
        *seen += 1;
        let plan = &self.plan;
        let in_scope = match plan.scope {
            FaultScope::All => true,
            FaultScope::ObjectGets => {
                matches!(kind, RequestKind::GetObject | RequestKind::RangedGet)
            }
            FaultScope::RangedGets => kind == RequestKind::RangedGet,
            FaultScope::Lists => kind == RequestKind::List,
            FaultScope::NthRequest(n) => self.requests == n,
        };
        // With `fail_once`, only a request's first sending may fail: its retries go through.
        if !in_scope || (plan.fail_once && (occurrence > 0 || self.faulted.contains(key))) {
            return None;
        }
        let draw = unit(splitmix64(
            plan.seed ^ fnv1a(key.as_bytes()) ^ occurrence.wrapping_mul(0x9e37_79b9_7f4a_7c15),
        ));
        let mut threshold = 0.0;
        let mut fault = None;
        for (p, candidate) in [
            (plan.p_503, Fault::Status503),
            (plan.p_500, Fault::Status500),
            (plan.p_reset, Fault::Reset),
            (plan.p_cut, Fault::Cut),
            (plan.p_slow_first_byte, Fault::SlowFirstByte),
        ] {
            threshold += p;
            if p > 0.0 && draw < threshold {
                fault = Some(candidate);
                break;
            }
        }
        let fault = fault?;
        self.faulted.insert(key.to_owned());
        let faults = &mut self.counters.faults;
        match fault {
            Fault::Status503 => faults.status_503 += 1,
            Fault::Status500 => faults.status_500 += 1,
            Fault::Reset => faults.reset += 1,
            Fault::Cut => faults.cut += 1,
            Fault::SlowFirstByte => faults.slow_first_byte += 1,
        }
        Some(fault)
    }
}

fn splitmix64(mut x: u64) -> u64 {
    x = x.wrapping_add(0x9e37_79b9_7f4a_7c15);
    x = (x ^ (x >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    x = (x ^ (x >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    x ^ (x >> 31)
}

fn fnv1a(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325, |h, &b| {
        (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3)
    })
}

/// Uniform in [0, 1) from the top 53 bits.
fn unit(x: u64) -> f64 {
    (x >> 11) as f64 / (1u64 << 53) as f64
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn classifies_s3_requests() {
        use RequestKind::*;
        assert_eq!(
            RequestKind::classify("GET", "/b/k/x.mcap", false),
            GetObject
        );
        assert_eq!(RequestKind::classify("GET", "/b/k", true), RangedGet);
        assert_eq!(
            RequestKind::classify("GET", "/b?list-type=2&prefix=a", false),
            List
        );
        assert_eq!(RequestKind::classify("GET", "/b", false), Other);
        assert_eq!(RequestKind::classify("GET", "/b/k?uploads", false), Other);
        assert_eq!(RequestKind::classify("HEAD", "/b/k", false), Head);
        assert_eq!(RequestKind::classify("PUT", "/b", false), Put);
        assert_eq!(RequestKind::classify("DELETE", "/b/k", false), Other);
    }

    #[test]
    fn fail_once_rate_is_near_p_and_deterministic() {
        let plan = FaultPlan {
            p_503: 0.1,
            fail_once: true,
            ..FaultPlan::default()
        };
        let run = || {
            let mut state = State::new(plan.clone());
            let first: Vec<bool> = (0..2000)
                .map(|i| {
                    let key = format!("GET /b/k{i} ");
                    state.decide(RequestKind::GetObject, &key).is_some()
                })
                .collect();
            // The retries all go through.
            for i in 0..2000 {
                let key = format!("GET /b/k{i} ");
                assert_eq!(state.decide(RequestKind::GetObject, &key), None);
            }
            first
        };
        let a = run();
        assert_eq!(a, run());
        let failed = a.iter().filter(|&&f| f).count();
        assert!((150..250).contains(&failed), "{failed} of 2000 failed");
    }

    #[test]
    fn distinct_bytes_count_each_byte_once() {
        let mut state = State::default();
        state.cover("/b/k", 10..20);
        state.cover("/b/k", 15..30); // overlaps: 10 new
        state.cover("/b/k", 30..35); // touches: 5 new
        state.cover("/b/k", 0..5);
        state.cover("/b/other", 0..5);
        assert_eq!(state.counters.distinct_get_bytes, 10 + 10 + 5 + 5 + 5);
        state.cover("/b/k", 0..40); // bridges the gap 5..10, extends to 40
        assert_eq!(state.counters.distinct_get_bytes, 35 + 5 + 5);
        assert_eq!(state.covered["/b/k"], vec![0..40]);
        state.reset_counters();
        state.cover("/b/k", 0..40);
        assert_eq!(state.counters.distinct_get_bytes, 40);
    }

    #[test]
    fn scope_and_validation() {
        let mut state = State::new(FaultPlan {
            p_500: 1.0,
            scope: FaultScope::NthRequest(2),
            ..FaultPlan::default()
        });
        let faults: Vec<_> = (0..3)
            .map(|_| state.decide(RequestKind::Head, "HEAD /b/k "))
            .collect();
        assert_eq!(faults, [None, Some(Fault::Status500), None]);
        assert_eq!(state.counters.head, 3);
        assert_eq!(state.counters.faults.status_500, 1);
        let bad = FaultPlan {
            p_503: 0.7,
            p_cut: 0.7,
            ..FaultPlan::default()
        };
        assert!(matches!(bad.validate(), Err(PlanError::Sum(_))));
    }
}
