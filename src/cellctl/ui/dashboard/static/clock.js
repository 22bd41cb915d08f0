// Times of day on the 24-hour clock, as a control room reads them (a browser's locale may
// say "8:53:05 PM"): HH:MM:SS, local time.
const two = (n) => String(n).padStart(2, "0");

export function timeOfDay(date) {
  return `${two(date.getHours())}:${two(date.getMinutes())}:${two(date.getSeconds())}`;
}

// A time.time() value (seconds) as HH:MM:SS; "" for none.
export function clockOf(seconds) {
  return seconds ? timeOfDay(new Date(seconds * 1000)) : "";
}

const DAYS = ["Sun", "Mon", "Tue", "Wed", "Thu", "Fri", "Sat"];

// An order's due time, short, local, on the 24-hour clock: "Fri 11-27 18:00" (its seconds
// only when it has some). The day and date: a due time is often days ahead, or behind.
export function dueTime(seconds) {
  const d = new Date(seconds * 1000);
  const secs = d.getSeconds() ? `:${two(d.getSeconds())}` : "";
  return `${DAYS[d.getDay()]} ${two(d.getMonth() + 1)}-${two(d.getDate())} `
    + `${two(d.getHours())}:${two(d.getMinutes())}${secs}`;
}

// Call `fn` every `ms` while the page is shown, and once at once when it is shown again: a
// page in a hidden tab or a locked screen reads nothing (the live subscription still keeps
// its status current), and is up to date the moment it is looked at.
export function whileShown(ms, fn) {
  let timer = null;
  const follow = () => {
    if (document.hidden) {
      clearInterval(timer);
      timer = null;
    } else if (timer === null) {
      timer = setInterval(fn, ms);
      return true;
    }
    return false;
  };
  document.addEventListener("visibilitychange", () => {
    if (follow()) {
      fn();
    }
  });
  follow();
}
