//! Bearer-token checks: a write token for ingest and control, a separate
//! read-only token for subscribe. Health and reflection stay open so probes
//! and `grpcurl list` work without credentials.

use std::sync::Arc;
use tonic::{Request, Status};

/// What a service needs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Access {
    /// Ingest and control: the write token.
    Write,
    /// Subscribe: the read-only token or the write token.
    Read,
}

/// The configured tokens.
#[derive(Clone)]
pub struct Tokens {
    inner: Arc<(Option<String>, Option<String>)>,
}

impl Tokens {
    /// `write`: ingest + control; `read`: subscribe only. `None`: not required.
    pub fn new(write: Option<String>, read: Option<String>) -> Tokens {
        let nonempty = |t: Option<String>| t.filter(|t| !t.is_empty());
        Tokens {
            inner: Arc::new((nonempty(write), nonempty(read))),
        }
    }

    /// Decides whether `presented` (the bearer token, if any) grants `access`.
    pub fn check(&self, access: Access, presented: Option<&str>) -> Result<(), Status> {
        let (write, read) = (&self.inner.0, &self.inner.1);
        let is = |t: &Option<String>| matches!((t, presented), (Some(t), Some(p)) if ct_eq(t, p));
        match access {
            Access::Write => match write {
                None => Ok(()),
                Some(_) if is(write) => Ok(()),
                Some(_) if is(read) => Err(Status::permission_denied(
                    "the read-only token allows Reports.Subscribe only",
                )),
                Some(_) => Err(missing_or_wrong(presented)),
            },
            Access::Read => {
                if write.is_none() && read.is_none() || is(write) || is(read) {
                    Ok(())
                } else {
                    Err(missing_or_wrong(presented))
                }
            }
        }
    }

    /// An interceptor enforcing `access` on every request of a service.
    pub fn interceptor(
        &self,
        access: Access,
    ) -> impl FnMut(Request<()>) -> Result<Request<()>, Status> + Clone + use<> {
        let tokens = self.clone();
        move |req: Request<()>| {
            let presented = req
                .metadata()
                .get("authorization")
                .and_then(|v| v.to_str().ok())
                .and_then(|v| {
                    v.strip_prefix("Bearer ")
                        .or_else(|| v.strip_prefix("bearer "))
                })
                .map(str::trim);
            tokens.check(access, presented)?;
            Ok(req)
        }
    }
}

fn missing_or_wrong(presented: Option<&str>) -> Status {
    match presented {
        None => Status::unauthenticated(
            "missing bearer token (metadata \"authorization: Bearer <token>\")",
        ),
        Some(_) => Status::unauthenticated("bearer token not recognised"),
    }
}

/// Compares without an early exit, so timing does not reveal a matching prefix.
fn ct_eq(a: &str, b: &str) -> bool {
    let (a, b) = (a.as_bytes(), b.as_bytes());
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

#[cfg(test)]
mod tests {
    use super::*;
    use tonic::Code;

    #[test]
    fn token_matrix() {
        let t = Tokens::new(Some("w".into()), Some("r".into()));
        let code = |a, p| t.check(a, p).err().map(|s| s.code());
        assert_eq!(code(Access::Write, Some("w")), None);
        assert_eq!(code(Access::Write, Some("r")), Some(Code::PermissionDenied));
        assert_eq!(code(Access::Write, Some("x")), Some(Code::Unauthenticated));
        assert_eq!(code(Access::Write, None), Some(Code::Unauthenticated));
        assert_eq!(code(Access::Read, Some("r")), None);
        assert_eq!(code(Access::Read, Some("w")), None);
        assert_eq!(code(Access::Read, Some("ww")), Some(Code::Unauthenticated));
        assert_eq!(code(Access::Read, None), Some(Code::Unauthenticated));
        let open = Tokens::new(None, None);
        assert!(open.check(Access::Write, None).is_ok() && open.check(Access::Read, None).is_ok());
    }
}
