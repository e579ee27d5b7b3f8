//! A raw gRPC client over HTTP/2 for abuse tests and the soak harness: it sends the bytes and
//! headers it is given, stops sending when told (a stalled upload), and reads the answer's
//! status wherever the server puts it (trailers-only or trailers). The typed [`crate::client`] is
//! for everything else.

use bytes::Bytes;
use tonic::{Code, Status};

type BoxError = Box<dyn std::error::Error + Send + Sync>;

/// The gRPC path of a call, e.g. `path("Complete")` = `/deocc.v1.Deocc/Complete`.
pub fn path(method: &str) -> String {
    format!("/deocc.v1.Deocc/{method}")
}

/// One message in gRPC's length-prefixed framing (uncompressed).
pub fn frame(message: &[u8]) -> Vec<u8> {
    let mut out = frame_header(message.len() as u32).to_vec();
    out.extend_from_slice(message);
    out
}

/// The 5-byte prefix announcing a message of `len` bytes (the message itself may never come).
pub fn frame_header(len: u32) -> [u8; 5] {
    let b = len.to_be_bytes();
    [0, b[0], b[1], b[2], b[3]]
}

/// An open call: its request body is sent piece by piece.
pub struct RawCall {
    send: h2::SendStream<Bytes>,
    response: h2::client::ResponseFuture,
    _connection: tokio::task::JoinHandle<()>,
}

/// What came back.
#[derive(Debug)]
pub struct RawAnswer {
    pub status: Status,
    /// The response messages' bytes, framing included.
    pub body: Vec<u8>,
}

impl RawCall {
    /// Opens `method` on `addr` (`host:port`) with extra `headers` (e.g. `authorization`).
    pub async fn open(
        addr: &str,
        method: &str,
        headers: &[(&str, &[u8])],
    ) -> Result<Self, BoxError> {
        let tcp = tokio::net::TcpStream::connect(addr).await?;
        let (client, connection) = h2::client::handshake(tcp).await?;
        let connection = tokio::spawn(async move {
            let _ = connection.await;
        });
        let mut client = client.ready().await?;
        let mut req = http::Request::builder()
            .method("POST")
            .uri(format!("http://{addr}{}", path(method)))
            .header("content-type", "application/grpc")
            .header("te", "trailers");
        for (k, v) in headers {
            req = req.header(*k, http::HeaderValue::from_bytes(v)?);
        }
        let (response, send) = client.send_request(req.body(())?, false)?;
        Ok(Self {
            send,
            response,
            _connection: connection,
        })
    }

    /// Sends `data`; `end` closes the request body.
    pub fn send(&mut self, data: &[u8], end: bool) -> Result<(), BoxError> {
        self.send.send_data(Bytes::copy_from_slice(data), end)?;
        Ok(())
    }

    /// Abandons the call (an RST_STREAM CANCEL, as a client that gives up).
    pub fn cancel(mut self) {
        self.send.send_reset(h2::Reason::CANCEL);
    }

    /// Waits for the answer and its status.
    pub async fn answer(self) -> Result<RawAnswer, BoxError> {
        let resp = self.response.await?;
        let (parts, mut body) = resp.into_parts();
        if let Some(status) = status_of(&parts.headers) {
            return Ok(RawAnswer {
                status,
                body: Vec::new(),
            });
        }
        let mut out = Vec::new();
        while let Some(chunk) = body.data().await {
            let chunk = chunk?;
            let _ = body.flow_control().release_capacity(chunk.len());
            out.extend_from_slice(&chunk);
        }
        let trailers = body.trailers().await?.unwrap_or_default();
        let status = status_of(&trailers)
            .unwrap_or_else(|| Status::unknown("the answer had no grpc-status"));
        Ok(RawAnswer { status, body: out })
    }
}

fn status_of(headers: &http::HeaderMap) -> Option<Status> {
    let code = headers.get("grpc-status")?.to_str().ok()?;
    if code == "0" {
        return Some(Status::new(Code::Ok, ""));
    }
    Status::from_header_map(headers)
}
