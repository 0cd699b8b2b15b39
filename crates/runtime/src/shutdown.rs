//! Shutdown as a value: every task of the daemon gets a [`Shutdown`] and
//! stops when it fires, instead of polling a global flag.
//!
//! The service holds the one [`ShutdownTrigger`]; it fires on SIGINT/SIGTERM,
//! at the end of a replay, or when a task fails. Async tasks `select!` on
//! [`Shutdown::recv`]; blocking threads (servo reads, inference) check
//! [`Shutdown::is_shutdown`] between iterations.

use tokio::sync::watch;

/// Fires the shutdown of every [`Shutdown`] made from it.
#[derive(Debug)]
pub struct ShutdownTrigger {
    sender: watch::Sender<bool>,
}

/// One task's view of the shutdown signal (cheap to clone).
#[derive(Debug, Clone)]
pub struct Shutdown {
    receiver: watch::Receiver<bool>,
}

impl ShutdownTrigger {
    /// A trigger and the first [`Shutdown`] listening to it.
    pub fn new() -> (ShutdownTrigger, Shutdown) {
        let (sender, receiver) = watch::channel(false);
        (ShutdownTrigger { sender }, Shutdown { receiver })
    }

    /// Another listener (for a task started later).
    pub fn subscribe(&self) -> Shutdown {
        Shutdown {
            receiver: self.sender.subscribe(),
        }
    }

    /// Ask every task to stop. Idempotent.
    pub fn fire(&self) {
        self.sender.send_replace(true);
    }
}

impl Shutdown {
    /// True once shutdown was requested (for blocking threads).
    pub fn is_shutdown(&self) -> bool {
        *self.receiver.borrow()
    }

    /// The underlying channel (true = stop), for components that take a
    /// plain `watch::Receiver<bool>` (the servo reader).
    pub fn watch(&self) -> watch::Receiver<bool> {
        self.receiver.clone()
    }

    /// Wait until shutdown is requested. Returns at once if it already was,
    /// or if the trigger was dropped (nobody can ask any more: stop too).
    pub async fn recv(&mut self) {
        // `wait_for` errs only when the sender is gone, which also means stop.
        let _ = self.receiver.wait_for(|stop| *stop).await;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn fires_every_listener_and_stays_fired() {
        let (trigger, mut first) = ShutdownTrigger::new();
        let mut second = trigger.subscribe();
        assert!(!first.is_shutdown());
        trigger.fire();
        first.recv().await;
        second.recv().await;
        assert!(first.is_shutdown() && second.is_shutdown());
        // A clone made after firing sees it too.
        let mut late = first.clone();
        late.recv().await;
    }

    #[tokio::test]
    async fn dropped_trigger_releases_waiters() {
        let (trigger, mut shutdown) = ShutdownTrigger::new();
        drop(trigger);
        shutdown.recv().await;
    }
}
