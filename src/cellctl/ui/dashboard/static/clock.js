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
