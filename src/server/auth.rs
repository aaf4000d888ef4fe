//! Bearer-token authentication: every mutating route needs the token; reads
//! are open to loopback clients and need the token from anywhere else.

use std::io::{Read, Write};
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use axum::extract::{ConnectInfo, Request, State};
use axum::http::{header, Method};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};

use super::error::ApiError;
use super::ServerError;

/// Name of the generated token file in the data directory.
pub const TOKEN_FILE: &str = "token";

/// The token and where it came from.
#[derive(Debug, Clone)]
pub struct Token {
    secret: Arc<str>,
    /// The file the token was read from, or generated into.
    pub path: PathBuf,
}

impl Token {
    /// The token itself, as clients send it in `Authorization: Bearer <token>`.
    pub fn secret(&self) -> &str {
        &self.secret
    }

    /// Constant-time comparison of a presented token.
    pub fn matches(&self, presented: &str) -> bool {
        let a = self.secret.as_bytes();
        let b = presented.as_bytes();
        if a.len() != b.len() {
            return false;
        }
        a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
    }
}

/// The token in a token file's text: one line of at least 16 visible
/// characters (surrounding whitespace ignored), or why not. The same rule
/// holds for the tokens of `rigd serve --peers`.
pub fn usable_secret(text: &str) -> Result<&str, &'static str> {
    let secret = text.trim();
    if secret.len() < 16 || secret.chars().any(|c| c.is_whitespace() || c.is_control()) {
        return Err("expected one line of at least 16 visible characters");
    }
    Ok(secret)
}

/// Reads the token from `token_file`, or from `DATA/token`, generating it
/// there (mode 0600) on first start.
pub fn load_or_create(token_file: Option<&Path>, data_dir: &Path) -> Result<Token, ServerError> {
    let read = |path: &Path| -> Result<Token, ServerError> {
        let text = rigd_core::read::read_text(path, rigd_core::read::TEXT_LIMIT).map_err(|e| {
            ServerError::Token {
                path: path.to_path_buf(),
                why: e.reason.to_string(),
            }
        })?;
        let secret = usable_secret(&text).map_err(|why| ServerError::Token {
            path: path.to_path_buf(),
            why: why.into(),
        })?;
        Ok(Token {
            secret: secret.into(),
            path: path.to_path_buf(),
        })
    };
    if let Some(path) = token_file {
        return read(path);
    }
    let path = data_dir.join(TOKEN_FILE);
    if path.exists() {
        return read(&path);
    }
    let mut bytes = [0u8; 32];
    std::fs::File::open("/dev/urandom")
        .and_then(|mut f| f.read_exact(&mut bytes))
        .map_err(|e| ServerError::Token {
            path: path.clone(),
            why: format!("cannot read random bytes: {e}"),
        })?;
    let secret = hex::encode(bytes);
    let write = || -> std::io::Result<()> {
        let mut opts = std::fs::OpenOptions::new();
        opts.write(true).create_new(true);
        #[cfg(unix)]
        {
            use std::os::unix::fs::OpenOptionsExt;
            opts.mode(0o600);
        }
        let mut f = opts.open(&path)?;
        f.write_all(secret.as_bytes())?;
        f.write_all(b"\n")?;
        f.sync_all()
    };
    write().map_err(|e| ServerError::Token {
        path: path.clone(),
        why: e.to_string(),
    })?;
    Ok(Token {
        secret: secret.into(),
        path,
    })
}

fn bearer(req: &Request) -> Option<&str> {
    let value = req.headers().get(header::AUTHORIZATION)?.to_str().ok()?;
    let (scheme, token) = value.split_once(' ')?;
    scheme
        .eq_ignore_ascii_case("bearer")
        .then_some(token.trim())
}

/// The middleware: mutating methods always need the token; reads need it
/// unless the client is on loopback.
pub async fn require_token(State(token): State<Token>, req: Request, next: Next) -> Response {
    let read = matches!(*req.method(), Method::GET | Method::HEAD | Method::OPTIONS);
    let loopback = req
        .extensions()
        .get::<ConnectInfo<SocketAddr>>()
        .map(|ConnectInfo(addr)| addr.ip().is_loopback())
        .unwrap_or(false);
    if read && loopback {
        return next.run(req).await;
    }
    match bearer(&req) {
        Some(t) if token.matches(t) => next.run(req).await,
        Some(_) => ApiError::unauthorized("wrong token").into_response(),
        None => ApiError::unauthorized(
            "this route needs `Authorization: Bearer <token>` (see the token file named in the daemon's log)",
        )
        .into_response(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use axum::body::Body;
    use axum::routing::{get, post};
    use axum::Router;
    use tower::ServiceExt;

    fn app(token: Token) -> Router {
        Router::new()
            .route("/r", get(|| async { "read" }))
            .route("/w", post(|| async { "write" }))
            .route_layer(axum::middleware::from_fn_with_state(token, require_token))
    }

    async fn call(app: Router, method: &str, path: &str, peer: &str, auth: Option<&str>) -> u16 {
        let mut req = Request::builder().method(method).uri(path);
        if let Some(a) = auth {
            req = req.header(header::AUTHORIZATION, a);
        }
        let mut req = req.body(Body::empty()).expect("request");
        let peer: SocketAddr = peer.parse().expect("addr");
        req.extensions_mut().insert(ConnectInfo(peer));
        app.oneshot(req).await.expect("response").status().as_u16()
    }

    #[tokio::test]
    async fn reads_open_on_loopback_only_and_writes_always_need_the_token() {
        let token = Token {
            secret: "s3cret-s3cret-s3cret".into(),
            path: PathBuf::from("token"),
        };
        let a = app(token);
        let good = Some("Bearer s3cret-s3cret-s3cret");
        assert_eq!(
            call(a.clone(), "GET", "/r", "127.0.0.1:5000", None).await,
            200
        );
        assert_eq!(call(a.clone(), "GET", "/r", "[::1]:5000", None).await, 200);
        assert_eq!(
            call(a.clone(), "GET", "/r", "192.0.2.7:5000", None).await,
            401
        );
        assert_eq!(
            call(a.clone(), "GET", "/r", "192.0.2.7:5000", good).await,
            200
        );
        assert_eq!(
            call(a.clone(), "POST", "/w", "127.0.0.1:5000", None).await,
            401
        );
        assert_eq!(
            call(
                a.clone(),
                "POST",
                "/w",
                "127.0.0.1:5000",
                Some("Bearer nope")
            )
            .await,
            401
        );
        assert_eq!(
            call(
                a.clone(),
                "POST",
                "/w",
                "127.0.0.1:5000",
                Some("bearer s3cret-s3cret-s3cret")
            )
            .await,
            200
        );
        assert_eq!(call(a, "POST", "/w", "192.0.2.7:5000", good).await, 200);
    }

    #[test]
    fn tokens_compare_whole() {
        let t = Token {
            secret: "abcdefghijklmnop".into(),
            path: PathBuf::new(),
        };
        assert!(t.matches("abcdefghijklmnop"));
        assert!(!t.matches("abcdefghijklmno"));
        assert!(!t.matches("abcdefghijklmnopq"));
        assert!(!t.matches(""));
    }

    #[test]
    fn a_generated_token_is_private_and_read_back() {
        let dir = tempfile::tempdir().expect("tempdir");
        let t = load_or_create(None, dir.path()).expect("token");
        assert_eq!(t.secret().len(), 64);
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            let mode = std::fs::metadata(dir.path().join(TOKEN_FILE))
                .expect("file")
                .permissions()
                .mode();
            assert_eq!(mode & 0o777, 0o600);
        }
        let again = load_or_create(None, dir.path()).expect("token");
        assert_eq!(again.secret(), t.secret());
        let short = dir.path().join("short");
        std::fs::write(&short, "abc").expect("write");
        assert!(load_or_create(Some(&short), dir.path()).is_err());
    }
}
