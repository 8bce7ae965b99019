//! `dnm linksim`: a radio link between the ground's and the rover's Zenoh endpoints, on one
//! machine and without root: a proxy that delays, caps the bandwidth, loses (seeded) and drops
//! out on a schedule, both ways.
//!
//! TCP: the proxy cannot drop bytes of a stream, so a lost segment costs what TCP pays for
//! it: the segment and everything behind it wait a retransmission timeout (doubling while the
//! retransmission is lost too). During an outage nothing passes and new connections wait; a
//! Zenoh session whose lease runs out closes its connection, as over a real radio.
//! UDP: each datagram is lost with the given probability, or dropped in an outage.

use std::collections::HashMap;
use std::io::{Read, Write};
use std::net::{SocketAddr, TcpListener, TcpStream, UdpSocket};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::Context;

#[derive(clap::Args, Debug, Clone)]
pub struct LinkArgs {
    /// Where the proxy listens (the side that connects uses this address).
    #[arg(long)]
    pub bind: SocketAddr,
    /// Where it forwards to (the side that listens).
    #[arg(long)]
    pub to: SocketAddr,
    /// Carry UDP datagrams instead of TCP streams.
    #[arg(long)]
    pub udp: bool,
    /// One-way delay, e.g. `300ms`.
    #[arg(long, default_value = "0ms")]
    pub delay: String,
    /// Bandwidth each way, e.g. `256kbit`, `2mbit` (default: unlimited).
    #[arg(long)]
    pub rate: Option<String>,
    /// Probability that a packet is lost, each way (0 to 1).
    #[arg(long, default_value_t = 0.0)]
    pub loss: f64,
    /// Outages: `10s/30s` is up 20 s, then down 10 s, every 30 s.
    #[arg(long)]
    pub outage: Option<String>,
    /// Seed of the losses.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Bytes a TCP direction holds in flight before the sender has to wait, as a socket buffer
    /// does: a slow link pushes back on its sender instead of queueing without end.
    #[arg(long, default_value_t = 64 * 1024)]
    pub buffer: usize,
}

/// The link's behaviour, parsed.
#[derive(Debug, Clone, Copy)]
pub struct Link {
    pub delay: Duration,
    /// Bytes per second; 0: unlimited.
    pub rate: f64,
    pub loss: f64,
    /// (down, period).
    pub outage: Option<(Duration, Duration)>,
    pub seed: u64,
    pub buffer: usize,
    pub start: Instant,
}

impl Link {
    pub fn parse(a: &LinkArgs) -> anyhow::Result<Self> {
        let ms = |s: &str| {
            dnm_netlist::parse_duration_ms(s)
                .with_context(|| format!("`{s}` is not a duration (e.g. `300ms`, `10s`)"))
        };
        let rate = match &a.rate {
            None => 0.0,
            Some(r) => parse_rate(r)?,
        };
        if !(0.0..1.0).contains(&a.loss) {
            anyhow::bail!("--loss {} must be from 0 up to (not including) 1", a.loss);
        }
        let outage = match &a.outage {
            None => None,
            Some(o) => {
                let (down, period) = o.split_once('/').with_context(|| {
                    format!("--outage `{o}`: write DOWN/PERIOD, e.g. `10s/30s`")
                })?;
                let (down, period) = (ms(down)?, ms(period)?);
                if down >= period || period == 0 {
                    anyhow::bail!("--outage `{o}`: the outage must be shorter than its period");
                }
                Some((Duration::from_millis(down), Duration::from_millis(period)))
            }
        };
        Ok(Self {
            delay: Duration::from_millis(ms(&a.delay)?),
            rate,
            loss: a.loss,
            outage,
            seed: a.seed,
            buffer: a.buffer.max(1500),
            start: Instant::now(),
        })
    }

    /// The end of the outage `t` falls in, if it falls in one.
    fn outage_end(&self, t: Instant) -> Option<Instant> {
        let (down, period) = self.outage?;
        let since = t.duration_since(self.start);
        let phase = Duration::from_nanos((since.as_nanos() % period.as_nanos()) as u64);
        (phase >= period - down).then(|| t + (period - phase))
    }
}

/// splitmix64: small, seeded, good enough for losses.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> f64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// One direction of the link: when it is free to send again, and when the last packet of a
/// stream arrived (a stream delivers in order).
#[derive(Debug, Clone, Copy)]
struct Way {
    free: Instant,
    last: Instant,
}

impl Way {
    fn new() -> Self {
        let now = Instant::now();
        Self {
            free: now,
            last: now,
        }
    }
}

/// When a packet of `len` bytes handed over now arrives, or `None` if it is lost for good
/// (datagrams). A lost segment of a stream arrives a retransmission timeout later (doubling
/// while the retransmission is lost too), and holds up what follows it, as in TCP; losses of
/// packets in flight together overlap.
fn schedule(
    link: &Link,
    rng: &mut Rng,
    way: &mut Way,
    len: usize,
    stream: bool,
) -> Option<Instant> {
    let mut tx = way.free.max(Instant::now());
    if link.rate > 0.0 {
        tx += Duration::from_secs_f64(len as f64 / link.rate);
    }
    way.free = tx;
    let mut arrive = tx + link.delay;
    if let Some(end) = link.outage_end(tx) {
        if !stream {
            return None;
        }
        arrive = end + link.delay;
    }
    if !stream {
        return (link.loss == 0.0 || rng.next() >= link.loss).then_some(arrive);
    }
    let mut rto = (link.delay * 2).max(Duration::from_millis(200));
    while link.loss > 0.0 && rng.next() < link.loss {
        arrive += rto;
        rto *= 2;
        if let Some(end) = link.outage_end(arrive - link.delay) {
            arrive = end + link.delay;
        }
    }
    arrive = arrive.max(way.last);
    way.last = arrive;
    Some(arrive)
}

pub fn run(args: &LinkArgs) -> anyhow::Result<()> {
    let link = Link::parse(args)?;
    println!(
        "link {} -> {} ({}): delay {:?}, rate {}, loss {:.0}%, outage {:?}, seed {}; Ctrl-C to stop",
        args.bind,
        args.to,
        if args.udp { "udp" } else { "tcp" },
        link.delay,
        args.rate.as_deref().unwrap_or("unlimited"),
        link.loss * 100.0,
        args.outage,
        link.seed
    );
    if args.udp {
        udp(link, args.bind, args.to)
    } else {
        tcp(link, args.bind, args.to)
    }
}

fn tcp(link: Link, listen: SocketAddr, to: SocketAddr) -> anyhow::Result<()> {
    let listener = TcpListener::bind(listen).with_context(|| format!("listening on {listen}"))?;
    let n = AtomicU64::new(0);
    for client in listener.incoming() {
        let Ok(client) = client else { continue };
        let k = n.fetch_add(1, Ordering::Relaxed);
        std::thread::spawn(move || {
            // A connection made during an outage waits for the link (SYNs are retried).
            if let Some(end) = link.outage_end(Instant::now()) {
                std::thread::sleep(end.saturating_duration_since(Instant::now()));
            }
            std::thread::sleep(link.delay * 2);
            let Ok(server) = TcpStream::connect(to) else {
                return;
            };
            let _ = client.set_nodelay(true);
            let _ = server.set_nodelay(true);
            let (Ok(c2), Ok(s2)) = (client.try_clone(), server.try_clone()) else {
                return;
            };
            let up = std::thread::spawn(move || pump(link, client, server, link.seed ^ (k << 1)));
            pump(link, s2, c2, link.seed ^ (k << 1) ^ 1);
            let _ = up.join();
        });
    }
    Ok(())
}

/// Carries one direction of a TCP connection through the link.
fn pump(link: Link, mut from: TcpStream, mut to: TcpStream, seed: u64) {
    let (tx, rx) = mpsc::channel::<(Instant, Vec<u8>)>();
    // Bytes taken from the sender and not yet delivered.
    let in_flight = Arc::new((Mutex::new(0usize), std::sync::Condvar::new()));
    let writer = {
        let in_flight = in_flight.clone();
        std::thread::spawn(move || {
            for (at, bytes) in rx {
                let wait = at.saturating_duration_since(Instant::now());
                if !wait.is_zero() {
                    std::thread::sleep(wait);
                }
                let ok = to.write_all(&bytes).is_ok();
                if let Ok(mut n) = in_flight.0.lock() {
                    *n = n.saturating_sub(bytes.len());
                    in_flight.1.notify_all();
                }
                if !ok {
                    break;
                }
            }
            let _ = to.shutdown(std::net::Shutdown::Both);
        })
    };
    let mut rng = Rng(seed);
    let mut way = Way::new();
    let mut buf = vec![0u8; 1400];
    loop {
        // A full buffer stops reading: the sender's socket fills and it has to wait.
        if let Ok(mut n) = in_flight.0.lock() {
            while *n >= link.buffer {
                match in_flight.1.wait_timeout(n, Duration::from_secs(1)) {
                    Ok((g, _)) => n = g,
                    Err(_) => return,
                }
            }
        }
        match from.read(&mut buf) {
            Ok(0) | Err(_) => break,
            Ok(n) => {
                if let Some(at) = schedule(&link, &mut rng, &mut way, n, true) {
                    if let Ok(mut f) = in_flight.0.lock() {
                        *f += n;
                    }
                    if tx.send((at, buf[..n].to_vec())).is_err() {
                        break;
                    }
                }
            }
        }
    }
    drop(tx);
    let _ = writer.join();
    let _ = from.shutdown(std::net::Shutdown::Both);
}

fn udp(link: Link, listen: SocketAddr, to: SocketAddr) -> anyhow::Result<()> {
    let front = Arc::new(UdpSocket::bind(listen).with_context(|| format!("binding {listen}"))?);
    let (tx, rx) = mpsc::channel::<(Instant, Arc<UdpSocket>, SocketAddr, Vec<u8>)>();
    // One sender delivers every datagram at its time (they are ordered by departure per way).
    std::thread::spawn(move || {
        let mut queue: Vec<(Instant, Arc<UdpSocket>, SocketAddr, Vec<u8>)> = Vec::new();
        loop {
            let next = queue.iter().map(|q| q.0).min();
            let item = match next {
                None => rx.recv().ok(),
                Some(at) => match rx.recv_timeout(at.saturating_duration_since(Instant::now())) {
                    Ok(i) => Some(i),
                    Err(mpsc::RecvTimeoutError::Timeout) => None,
                    Err(mpsc::RecvTimeoutError::Disconnected) => return,
                },
            };
            if let Some(i) = item {
                queue.push(i);
            }
            let now = Instant::now();
            queue.sort_by_key(|q| q.0);
            while queue.first().is_some_and(|q| q.0 <= now) {
                let (_, sock, dest, bytes) = queue.remove(0);
                let _ = sock.send_to(&bytes, dest);
            }
        }
    });
    let backs: Arc<Mutex<HashMap<SocketAddr, Arc<UdpSocket>>>> = Arc::default();
    let mut rng = Rng(link.seed);
    let mut way = Way::new();
    let mut buf = vec![0u8; 65536];
    loop {
        let (n, client) = front.recv_from(&mut buf).context("receiving")?;
        let back = {
            let Ok(mut b) = backs.lock() else { break };
            if let Some(s) = b.get(&client) {
                s.clone()
            } else {
                let s = Arc::new(UdpSocket::bind("0.0.0.0:0").context("binding")?);
                b.insert(client, s.clone());
                // Answers from the far side come back through the link too.
                let (front, s2, tx) = (front.clone(), s.clone(), tx.clone());
                std::thread::spawn(move || {
                    let mut rng = Rng(link.seed ^ 0x5555);
                    let mut way = Way::new();
                    let mut buf = vec![0u8; 65536];
                    while let Ok((n, _)) = s2.recv_from(&mut buf) {
                        if let Some(at) = schedule(&link, &mut rng, &mut way, n, false) {
                            let _ = tx.send((at, front.clone(), client, buf[..n].to_vec()));
                        }
                    }
                });
                s
            }
        };
        if let Some(at) = schedule(&link, &mut rng, &mut way, n, false) {
            let _ = tx.send((at, back, to, buf[..n].to_vec()));
        }
    }
    Ok(())
}

/// A link rate such as `256kbit` or `2mbit` (bit, kbit, mbit a second), in bytes a second.
pub(crate) fn parse_rate(r: &str) -> anyhow::Result<f64> {
    let r = r.to_ascii_lowercase();
    let (num, unit) = r.split_at(r.find(|c: char| c.is_ascii_alphabetic()).unwrap_or(r.len()));
    let n: f64 = num
        .parse()
        .with_context(|| format!("rate `{r}`: e.g. `256kbit`"))?;
    let bits = match unit {
        "bit" | "" => n,
        "kbit" => n * 1e3,
        "mbit" => n * 1e6,
        _ => anyhow::bail!("rate `{r}`: use bit, kbit or mbit"),
    };
    if !(bits.is_finite() && bits > 0.0) {
        anyhow::bail!("rate `{r}`: give a rate above zero, e.g. `256kbit`");
    }
    Ok(bits / 8.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn link(delay_ms: u64, rate: f64, loss: f64, outage: Option<(u64, u64)>) -> Link {
        Link {
            delay: Duration::from_millis(delay_ms),
            rate,
            loss,
            outage: outage.map(|(d, p)| (Duration::from_millis(d), Duration::from_millis(p))),
            seed: 1,
            buffer: 65536,
            start: Instant::now(),
        }
    }

    #[test]
    fn delay_and_bandwidth_add_up() {
        let l = link(300, 1000.0, 0.0, None);
        let (mut rng, mut way) = (Rng(1), Way::new());
        let t0 = Instant::now();
        let a = schedule(&l, &mut rng, &mut way, 500, true).unwrap();
        let b = schedule(&l, &mut rng, &mut way, 500, true).unwrap();
        // 500 bytes at 1000 B/s, then the delay; the second waits for the first.
        assert!(a - t0 >= Duration::from_millis(800), "{:?}", a - t0);
        assert!(b - a >= Duration::from_millis(499), "{:?}", b - a);
    }

    #[test]
    fn a_stream_loses_nothing_and_stays_in_order_a_datagram_is_lost() {
        let l = link(10, 0.0, 0.5, None);
        let (mut rng, mut way) = (Rng(7), Way::new());
        let arrivals: Vec<Instant> = (0..200)
            .map(|_| schedule(&l, &mut rng, &mut way, 100, true).unwrap())
            .collect();
        assert!(arrivals.windows(2).all(|w| w[0] <= w[1]));
        let (mut rng, mut way) = (Rng(7), Way::new());
        let delivered = (0..1000)
            .filter(|_| schedule(&l, &mut rng, &mut way, 100, false).is_some())
            .count();
        assert!(
            (400..600).contains(&delivered),
            "{delivered} of 1000 at 50% loss"
        );
    }

    #[test]
    fn an_outage_holds_a_stream_and_drops_datagrams() {
        // Down for the last 900 ms of every second; now is 200 ms into it: down.
        let mut l = link(0, 0.0, 0.0, Some((900, 1000)));
        l.start = Instant::now() - Duration::from_millis(200);
        let (mut rng, mut way) = (Rng(1), Way::new());
        assert!(schedule(&l, &mut rng, &mut way, 10, false).is_none());
        let at = schedule(&l, &mut rng, &mut way, 10, true).unwrap();
        assert!(
            at >= l.start + Duration::from_millis(1000),
            "held until the outage ends"
        );
    }
}
